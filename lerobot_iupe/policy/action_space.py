"""The action space a supervised run reads from its dataset when it has no env, and the check of the binary
dimensions of a continuous action."""

from __future__ import annotations

import numpy as np
from lerobot.utils.constants import ACTION, OBS_STATE


def action_space_from_dataset(config, dataset_meta) -> None:
    """Set ``config``'s action space (an ``IUPEConfig``) from a labelled dataset without an env: integer actions
    are ids 0 … max (LeRobot's stats), float actions a box spanning the data (a constant dimension gets ±0.5 around
    its value). For the arm model (joint positions) the box also spans the joints' states and half its width more
    on each side: labels are clipped into it, and a few labelled episodes rarely reach every pose an arm will."""
    feature = dataset_meta.features[ACTION]
    stats = (dataset_meta.stats or {}).get(ACTION)
    if stats is None:
        raise ValueError(f"the dataset {dataset_meta.root} has no stats for '{ACTION}' (meta/stats.json)")
    low = np.asarray(stats["min"], dtype=np.float64).reshape(-1)
    high = np.asarray(stats["max"], dtype=np.float64).reshape(-1)
    if not feature["dtype"].startswith("float"):
        config.n_actions = int(high.max()) + 1
        return
    if getattr(config, "joint_idm", False):
        state = dataset_meta.stats[OBS_STATE]
        columns = config.joint_state_columns
        low = np.minimum(low, np.asarray(state["min"], dtype=np.float64).reshape(-1)[columns])
        high = np.maximum(high, np.asarray(state["max"], dtype=np.float64).reshape(-1)[columns])
        low, high = low - 0.5 * (high - low), high + 0.5 * (high - low)
    flat = high - low < 1e-6
    config.action_low = [float(x) for x in np.where(flat, low - 0.5, low)]
    config.action_high = [float(x) for x in np.where(flat, high + 0.5, high)]
    names = feature_names(feature)
    dim = len(config.action_low)
    config.action_names = [str(n) for n in names] if names and len(names) == dim else [f"a{i}" for i in range(dim)]


def feature_names(feature: dict | None) -> list[str] | None:
    """A LeRobot feature's value names (``names`` is a list, or ``{"motors": [...]}`` in older datasets)."""
    names = (feature or {}).get("names")
    if isinstance(names, dict):
        names = next(iter(names.values()), None)
    return [str(n) for n in names] if isinstance(names, list) else None


def check_binary_action_dims(config) -> None:
    """``config.binary_action_dims`` must name dimensions of a continuous action."""
    if not config.binary_action_dims:
        return
    if not config.is_continuous:
        raise ValueError(
            f"--policy.binary_action_dims={config.binary_action_dims} applies to continuous (Box) actions; this "
            f"action space is discrete ({config.n_actions} actions): leave it empty"
        )
    outside = [d for d in config.binary_action_dims if d >= config.action_dim]
    if outside:
        names = config.action_names or [f"a{i}" for i in range(config.action_dim)]
        raise ValueError(
            f"--policy.binary_action_dims names dimension(s) {outside}, but the action has {config.action_dim} "
            f"(0 … {config.action_dim - 1}: {names})"
        )
