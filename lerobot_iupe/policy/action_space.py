"""The action space a supervised run reads from its dataset when it has no env, and the check of the binary
dimensions of a continuous action."""

from __future__ import annotations

import numpy as np
from lerobot.utils.constants import ACTION


def action_space_from_dataset(config, dataset_meta) -> None:
    """Set ``config``'s action space (an ``IUPEConfig``) from a labelled dataset without an env: integer actions
    are ids 0 … max (LeRobot's stats), float actions a box spanning the data (a constant dimension gets ±0.5 around
    its value)."""
    feature = dataset_meta.features[ACTION]
    stats = (dataset_meta.stats or {}).get(ACTION)
    if stats is None:
        raise ValueError(f"the dataset {dataset_meta.root} has no stats for '{ACTION}' (meta/stats.json)")
    low = np.asarray(stats["min"], dtype=np.float64).reshape(-1)
    high = np.asarray(stats["max"], dtype=np.float64).reshape(-1)
    if not feature["dtype"].startswith("float"):
        config.n_actions = int(high.max()) + 1
        return
    flat = high - low < 1e-6
    config.action_low = [float(x) for x in np.where(flat, low - 0.5, low)]
    config.action_high = [float(x) for x in np.where(flat, high + 0.5, high)]
    names = feature.get("names")
    if isinstance(names, dict):  # LeRobot also writes {"motors": [...]}
        names = next(iter(names.values()), None)
    dim = len(config.action_low)
    config.action_names = [str(n) for n in names] if names and len(names) == dim else [f"a{i}" for i in range(dim)]


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
