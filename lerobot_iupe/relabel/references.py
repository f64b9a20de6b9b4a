"""The simplest fits beside the IDM, on a dataset that already has actions (``--dry_run=true``): for the linear-first
model (``policy.joint_idm``), per joint, the plain ridge regression fitted on the IDM's own labelled frames and
window, the best copy of a future state of the same name a_t ≈ s_{t+k} (none for an action whose name is not a
state's: its units are another arm's) and the best difference copy of the column of the same name or stem (else of
the column the IDM follows). A user sees at once whether the IDM earns its place."""

from __future__ import annotations

import numpy as np
import torch

from lerobot_iupe.data.readers import window_indices
from lerobot_iupe.policy.action_sources import CAMERA, max_lag, named_sources, stem_sources
from lerobot_iupe.policy.algorithm import r_squared


def per_dimension_r2(predicted: np.ndarray, true: np.ndarray) -> list[float]:
    return [r_squared(predicted[:, d], true[:, d]) for d in range(true.shape[1])]


def episode_rows(bounds: list[tuple[int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(first row, last row, episode) of every row of the dataset, in row order."""
    base = bounds[0][0] if bounds else 0
    lengths = [end - first for first, end in bounds]
    first = np.repeat([first - base for first, _ in bounds], lengths)
    last = np.repeat([end - 1 - base for _, end in bounds], lengths)
    return first, last, np.repeat(np.arange(len(bounds)), lengths)


def best_copies(
    states: np.ndarray, actions: np.ndarray, columns: list[int | None], bounds, rows: np.ndarray, longest: int
) -> list[tuple[float, int]]:
    """Per action dimension, (R², k) of the best copy a_t ≈ s_{t+k}, k = 0 … ``longest`` (clamped into the
    episode); (NaN, -1) where ``columns`` has no column."""
    first, last, _ = episode_rows(bounds)
    best = [(-np.inf, 0) if column is not None else (float("nan"), -1) for column in columns]
    for k in range(longest + 1):
        later = np.clip(rows + k, first[rows], last[rows])
        for j, column in enumerate(columns):
            if column is not None:
                best[j] = max(best[j], (r_squared(states[later, column], actions[rows, j]), k))
    return best


def best_difference_copies(
    states: np.ndarray,
    actions: np.ndarray,
    columns: list[int | None],
    bounds,
    rows: np.ndarray,
    lowest: int,
    longest: int,
) -> list[tuple[float, int]]:
    """Per action dimension, (R², d) of the best difference copy a_t ≈ g·(s_{t+d+1} − s_{t+d}) + b, d = ``lowest`` …
    ``longest`` − 1 (clamped into the episode), g and b fitted by least squares on these rows (the simplest fit of a
    velocity or a delta; two numbers, so hardly flattered by fitting where it is scored); (NaN, -99) where
    ``columns`` has no column."""
    first, last, _ = episode_rows(bounds)
    best = [(-np.inf, 0) if column is not None else (float("nan"), -99) for column in columns]
    for d in range(lowest, longest):
        later = np.clip(rows + d + 1, first[rows], last[rows])
        now = np.clip(rows + d, first[rows], last[rows])
        for j, column in enumerate(columns):
            if column is None:
                continue
            source = states[later, column].astype(np.float64) - states[now, column]
            design = np.stack([source, np.ones_like(source)], axis=1)
            coef, *_ = np.linalg.lstsq(design, actions[rows, j].astype(np.float64), rcond=None)
            best[j] = max(best[j], (r_squared(design @ coef, actions[rows, j]), d))
    return best


@torch.no_grad()
def joint_references(
    policy, states: np.ndarray, actions: np.ndarray, bounds, rows: np.ndarray, state_names: list[str] | None = None
) -> dict:
    """{"ridge": [R² per dimension], "copy": [R² per dimension], "copy_lag": [k per dimension], "lag": [the IDM's
    lag per dimension]} on ``rows`` (those with a successor): the references of the linear-first model's labels."""
    config = policy.config
    first, last, _ = episode_rows(bounds)
    window = torch.as_tensor(states[window_indices(rows, config.idm_window, first[rows], last[rows])])
    ridge = policy.idm_encoder.reference(window.to(policy.device_of_weights)).cpu().numpy()
    named = named_sources(config.action_names, state_names) if state_names else [None] * config.action_dim
    stems = stem_sources(config.action_names, state_names) if state_names else [None] * config.action_dim
    # A dimension named after no column: the difference copy of the column the IDM found it follows (any units).
    sources = zip(stems, config.joint_state_columns, config.source_kinds, strict=True)
    stems = [stem if stem is not None or kind == CAMERA else column for stem, column, kind in sources]
    copies = best_copies(states, actions, named, bounds, rows, max_lag(config.fps))
    lowest = -min(1, config.idm_context or 0)
    differences = best_difference_copies(states, actions, stems, bounds, rows, lowest, max_lag(config.fps))
    return {
        "ridge": per_dimension_r2(ridge, actions[rows]),
        "copy": [score for score, _ in copies],
        "copy_lag": [lag for _, lag in copies],
        "difference": [score for score, _ in differences],
        "difference_lag": [lag for _, lag in differences],
        "lag": list(config.idm_joint_lags),
        "source": config.source_kinds,
    }


def thumbnail_references(policy, thumbnails: np.ndarray | None, actions: np.ndarray, rows: np.ndarray) -> list[float]:
    """Per dimension, R² on ``rows`` of the camera dimensions' thumbnail ridge (``camera_reference.py``; its
    predictions ``thumbnails``, one column per camera dimension); NaN for every other dimension, and for a checkpoint
    saved before it existed."""
    scores = [float("nan")] * policy.config.action_dim
    if thumbnails is None or not bool(policy.idm_camera.reference.fitted):
        return scores
    actions = actions.reshape(len(actions), -1)
    for column, dim in enumerate(policy.config.camera_dims):
        scores[dim] = r_squared(thumbnails[rows, column], actions[rows, dim])
    return scores


def linear_part_references(policy, linear: np.ndarray, actions: np.ndarray, rows: np.ndarray) -> dict:
    """The references of an IDM with a linear part (``--policy.idm_linear_part``): that ridge alone, fitted on the
    IDM's labelled frames and window, R² on ``rows`` per dimension (NaN on a binary one, which has none); no copies."""
    count = policy.config.action_dim
    actions = actions.reshape(len(actions), -1)
    ridge = per_dimension_r2(linear[rows], actions[rows])
    binary = policy.idm_head.binary.cpu().numpy()
    return {
        "ridge": [float("nan") if binary[d] else ridge[d] for d in range(count)],
        "copy": [float("nan")] * count, "copy_lag": [-1] * count, "lag": [None] * count,
        "source": ["window (network on its linear part)"] * count,
    }  # fmt: skip
