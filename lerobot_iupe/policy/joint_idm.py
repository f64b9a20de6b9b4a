"""The inverse dynamics model of a position-controlled arm: where the action and ``observation.state`` name the same
joints (LeRobot's ``<joint>.pos``), a_t is the leader's position, which the follower reaches a few frames later.

The model is a_t = s_{t+lag} + ridge(window) + gate ⊙ net(window): a copy of the state at the lag where the action
best matches a future state (chosen from the labelled data), a ridge regression's correction over the window
(closed form, its strength chosen per joint on held-out blocks of the episodes), and a small network per joint that
reads that joint's own window, whose correction is kept per joint only as far as it helps on labelled frames it did
not train on (``gate``). The linear part extrapolates to poses the labelled episodes never reached, as a linear fit
does; one network over every joint's window at once lost to the ridge alone on held-out episodes (gripper 0.85–0.91
against 0.92–0.93, wrist_roll 0.988 against 0.9995), one per joint did not (scripts/measure_arm_networks.py). A
plain ridge regression on the same window is kept beside it as the reference that relabelling reports
(``reference``)."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

# The longest lag searched: 0.35 s, well past the delays measured on SO-100/101 arms (about 0.13 s); 10 frames at least.
MAX_LAG_SECONDS = 0.35
RIDGE_ALPHAS = tuple(10.0**p for p in range(-3, 6))
MAX_FOLDS = 20
BLOCKS = 10
# The reference a user would fit first: a ridge regression with scikit-learn's default strength, standardised inputs.
REFERENCE_ALPHA = 1.0
# Share of each labelled episode, at its end, on which the network's gate is judged (it never trains on them).
GATE_SHARE = 0.2


def joint_state_columns(action_names: list[str] | None, state_names: list[str] | None) -> list[int] | None:
    """For each action dimension, the ``observation.state`` column of the same name; None unless every action
    dimension has one (an arm whose actions are joint positions)."""
    if not action_names or not state_names:
        return None
    position = {name: i for i, name in enumerate(state_names)}
    if any(name not in position for name in action_names):
        return None
    return [position[name] for name in action_names]


def max_lag(fps: float | None) -> int:
    """The longest lag searched at ``fps`` frames per second (``MAX_LAG_SECONDS``; 10 frames at least)."""
    return max(10, math.ceil(MAX_LAG_SECONDS * (fps or 30)))


def copy_errors(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> np.ndarray:
    """Mean absolute difference between a_t and s_{t+k} for k = 0 … ``longest`` (each joint scaled by its actions'
    spread, then averaged over joints), over the frames whose t+k lies in their episode."""
    spread = actions.std(axis=0) + 1e-6
    errors = []
    for k in range(longest + 1):
        same = episodes[k:] == episodes[: len(episodes) - k]
        if not same.any():
            errors.append(np.inf)
            continue
        gap = np.abs(actions[: len(actions) - k][same] - states[k:][same][:, columns]) / spread
        errors.append(float(gap.mean()))
    return np.asarray(errors)


def best_copy_lag(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> int:
    """The k at which s_{t+k} best matches a_t (``copy_errors``): how long the follower takes to reach the leader."""
    return int(np.argmin(copy_errors(states, actions, episodes, columns, longest)))


def fit_ridge(
    features: np.ndarray, targets: np.ndarray, groups: np.ndarray, alphas: tuple[float, ...] = RIDGE_ALPHAS
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ridge regression targets ≈ features @ W + b on standardised features (the intercept not penalised), the
    strength of each target column chosen from ``alphas`` by the squared error of its held-out predictions: each
    episode (``groups``, in frame order) cut into ``BLOCKS`` contiguous blocks, one block left out at a time (over
    ``MAX_FOLDS`` blocks, that many folds of them). Blocks rather than whole episodes: with two labelled episodes,
    two folds chose the strength by chance. Each fold is solved from per-fold sums (ZᵀZ, Zᵀy), so the cost does not
    grow with folds × frames. Returns W and b in the features' own units, the alphas and their held-out squared
    errors."""
    features, targets = np.asarray(features, np.float64), np.asarray(targets, np.float64)
    mean, std = features.mean(axis=0), features.std(axis=0) + 1e-6
    scaled = np.concatenate([(features - mean) / std, np.ones((len(features), 1))], axis=1)
    folds = episode_blocks(groups) % MAX_FOLDS
    stats = [
        (scaled[fold].T @ scaled[fold], scaled[fold].T @ targets[fold], (targets[fold] ** 2).sum(axis=0))
        for fold in (folds == f for f in np.unique(folds))
    ]
    gram, moment = sum(g for g, _, _ in stats), sum(m for _, m, _ in stats)
    penalty = np.diag(np.r_[np.ones(features.shape[1]), 0.0])
    errors = np.zeros((len(alphas), targets.shape[1]))
    for n, alpha in enumerate(alphas):
        for fold_gram, fold_moment, fold_square in stats:
            coef = np.linalg.solve(gram - fold_gram + alpha * penalty, moment - fold_moment)
            predicted_square = (coef * (fold_gram @ coef)).sum(axis=0)
            errors[n] += fold_square - 2.0 * (coef * fold_moment).sum(axis=0) + predicted_square
    chosen = errors.argmin(axis=0)
    coef = np.zeros((scaled.shape[1], targets.shape[1]))
    for n in np.unique(chosen):
        coef[:, chosen == n] = np.linalg.solve(gram + alphas[n] * penalty, moment[:, chosen == n])
    weight = coef[:-1] / std[:, None]
    held_out = errors[chosen, np.arange(targets.shape[1])]
    return weight, coef[-1] - mean @ weight, np.asarray(alphas)[chosen], held_out


def episode_blocks(groups: np.ndarray) -> np.ndarray:
    """A block number per frame: each episode's frames (in order) cut into ``BLOCKS`` contiguous blocks."""
    episodes, index = np.unique(groups, return_inverse=True)
    index = index.reshape(-1)
    position = np.zeros(len(groups), dtype=np.int64)
    for episode in range(len(episodes)):
        rows = np.flatnonzero(index == episode)
        position[rows] = np.arange(len(rows)) * BLOCKS // max(len(rows), 1)
    return index * BLOCKS + position


def gate_weights(residual: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """Per joint, the share w ∈ [0, 1] of the network's ``correction`` that minimises the squared error of
    ``residual − w · correction`` (what the linear part leaves, on frames the network did not train on)."""
    fit = (residual * correction).sum(axis=0) / np.maximum((correction**2).sum(axis=0), 1e-12)
    return np.clip(fit, 0.0, 1.0)


class JointIDM(nn.Module):
    """a_t from the window of joint states (B, F, D) at the config's offsets (raw units): copy of s_{t+lag} plus the
    ridge's correction (buffers, fitted once by ``fit``) plus the gated per-joint network; ``forward`` returns the
    network's per-joint correction (B, A), which the IDM head turns into the action's scaled units; ``prior`` is
    the linear part in raw units."""

    def __init__(self, offsets: list[int], lag: int, columns: list[int], state_dim: int, hidden: int):
        super().__init__()
        frames, joints = len(offsets), len(columns)
        self.copy_frame = offsets.index(lag)
        self.register_buffer("columns", torch.as_tensor(columns, dtype=torch.long), persistent=False)
        features = frames * state_dim
        for name, shape in (("weight", (features, joints)), ("reference_weight", (features, joints))):
            self.register_buffer(name, torch.zeros(shape))
        for name in ("bias", "reference_bias", "gate"):
            self.register_buffer(name, torch.zeros(joints))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        # The joints' mean and spread: the network reads standardised windows.
        self.register_buffer("center", torch.zeros(state_dim))
        self.register_buffer("scale", torch.ones(state_dim))
        # One small MLP per joint over that joint's own window (grouped 1×1 convolutions), its output starting at 0.
        self.net = nn.Sequential(
            nn.Conv1d(joints * frames, joints * hidden, 1, groups=joints),
            nn.ReLU(),
            nn.Conv1d(joints * hidden, joints * hidden, 1, groups=joints),
            nn.ReLU(),
            nn.Conv1d(joints * hidden, joints, 1, groups=joints),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def prior(self, window: Tensor) -> Tensor:
        """Copy plus ridge correction (B, A), raw action units."""
        flat = window.float().flatten(1)
        return window[:, self.copy_frame, self.columns].float() + flat @ self.weight + self.bias

    def reference(self, window: Tensor) -> Tensor:
        """The plain ridge regression on the same window (B, A): the simplest fit, reported beside the model."""
        return window.float().flatten(1) @ self.reference_weight + self.reference_bias

    def forward(self, window: Tensor) -> Tensor:
        """The network's per-joint correction (B, A): each joint reads its own window, standardised."""
        own = (window.float()[:, :, self.columns] - self.center[self.columns]) / self.scale[self.columns]
        return self.net(own.transpose(1, 2).reshape(len(own), -1, 1)).squeeze(-1)

    def fit(self, windows: np.ndarray, actions: np.ndarray, episodes: np.ndarray) -> dict[str, list[float]]:
        """The linear parts in closed form from labelled windows (N, F, D) and actions (N, A): per joint, the ridge
        on the residual a_t − s_{t+lag} (shrunk towards the copy) or on a_t itself, whichever predicts held-out
        blocks better (``ridge_alpha``: its strength, negative for the fit on a_t), and the plain reference ridge
        on a_t (``REFERENCE_ALPHA``)."""
        flat = windows.reshape(len(windows), -1).astype(np.float64)
        columns = self.columns.cpu().numpy()
        copy = np.zeros((flat.shape[1], len(columns)))  # the copy of s_{t+lag} as a linear map of the window
        copy[self.copy_frame * windows.shape[2] + columns, np.arange(len(columns))] = 1.0
        weight, bias, alpha, error = fit_ridge(flat, actions - flat @ copy, episodes)
        # A joint whose held-out error is lower without the copy (shrunk towards 0, not towards the copy) takes
        # that fit: the linear part is then the better of the two by the same cross-validation.
        plain_weight, plain_bias, plain_alpha, plain_error = fit_ridge(flat, actions, episodes)
        plain = plain_error < error
        weight = np.where(plain, plain_weight - copy, weight)
        bias, alpha = np.where(plain, plain_bias, bias), np.where(plain, -plain_alpha, alpha)
        reference_weight, reference_bias, *_ = fit_ridge(flat, actions, episodes, (REFERENCE_ALPHA,))
        device = self.weight.device
        as_buffer = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)  # noqa: E731
        self.weight.copy_(as_buffer(weight))
        self.bias.copy_(as_buffer(bias))
        self.reference_weight.copy_(as_buffer(reference_weight))
        self.reference_bias.copy_(as_buffer(reference_bias))
        self.center.copy_(as_buffer(windows.reshape(-1, windows.shape[-1]).mean(axis=0)))
        self.scale.copy_(as_buffer(windows.reshape(-1, windows.shape[-1]).std(axis=0) + 1e-3))
        self.fitted.fill_(True)
        return {"ridge_alpha": alpha.tolist()}
