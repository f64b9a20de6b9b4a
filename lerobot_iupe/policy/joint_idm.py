"""The linear-first inverse dynamics model of continuous actions read from a vector state: a position-controlled
arm's leader (LeRobot's ``<joint>.pos`` in both ``action`` and ``observation.state``), a leader of another arm (other
names, another number of joints), a humanoid's arms and hands.

Each action dimension j has a *source*: the state column of the same name, or else the column it most resembles
(the largest |correlation| between a_t and a later state, over columns and lags), and a *lag* of its own: where a_t
best matches s_{t+lag}. The model is a_t = copy_j + linear_j(window) + gate_j · net_j(window): the copy of the
source at its lag (its own units for a joint of the same name, an affine map of them otherwise), a ridge
regression's correction solved in closed form, and a small network per joint over its source's window whose
correction is kept only as far as it helps on labelled frames it did not train on (``gate``).

The correction is one of two candidates per joint, both shrunk toward the copy: a ridge on the joint's own window
(physically grounded) or a ridge over every state column's window. The second is taken only where it predicts
held-out *episodes* clearly better (``CLEARLY_BETTER``): on a new episode a joint that barely moved in the labelled
ones still follows its own state, and a fit over many columns from few episodes extrapolates worse (on a real
humanoid, a ridge over all 26 joints scored R² 0.852 where each joint's own window scored 0.980). A plain ridge on the
same window (``reference``) is kept beside it as the simplest fit that relabelling reports."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor, nn

# The longest lag searched and the window's reach: 0.35 s, well past the delays measured on real arms (about 0.13 s on
# an SO-101, up to 0.33 s on a humanoid's fingers); 10 frames at least.
MAX_LAG_SECONDS = 0.35
RIDGE_ALPHAS = tuple(10.0**p for p in range(-3, 6))
MAX_FOLDS = 20
BLOCKS = 10
# The reference a user would fit first: a ridge regression with scikit-learn's default strength, standardised inputs.
REFERENCE_ALPHA = 1.0
# Share of each labelled episode, at its end, on which the network's gate is judged (it never trains on them).
GATE_SHARE = 0.2
# A differently-named action dimension follows a state column when their |correlation| (at the best lag) reaches this.
RESEMBLANCE = 0.8
# The fit over every column replaces the joint's own window only where its held-out error is below this share of it.
CLEARLY_BETTER = 0.8


def named_sources(action_names: list[str] | None, state_names: list[str] | None) -> list[int | None]:
    """For each action dimension, the state column of the same name, or None."""
    position = {name: i for i, name in enumerate(state_names or [])}
    return [position.get(name) for name in action_names or []]


def max_lag(fps: float | None) -> int:
    """The longest lag searched at ``fps`` frames per second (``MAX_LAG_SECONDS``; 10 frames at least)."""
    return max(10, math.ceil(MAX_LAG_SECONDS * (fps or 30)))


def _lagged_pairs(episodes: np.ndarray, k: int) -> np.ndarray:
    """Rows t whose t+k lies in the same episode."""
    return np.flatnonzero(episodes[k:] == episodes[: len(episodes) - k])


def joint_copy_errors(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> np.ndarray:
    """(longest + 1, joints): mean absolute difference between a_t and s_{t+k} for k = 0 … ``longest``, each joint
    scaled by its actions' spread, over the frames whose t+k lies in their episode (inf where none does)."""
    spread = actions.std(axis=0) + 1e-6
    errors = np.full((longest + 1, actions.shape[1]), np.inf)
    for k in range(longest + 1):
        rows = _lagged_pairs(episodes, k)
        if len(rows):
            errors[k] = (np.abs(actions[rows] - states[rows + k][:, columns]) / spread).mean(axis=0)
    return errors


def copy_errors(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> np.ndarray:
    """``joint_copy_errors`` averaged over joints: one error per k."""
    return joint_copy_errors(states, actions, episodes, columns, longest).mean(axis=1)


def best_copy_lag(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> int:
    """The k at which s_{t+k} best matches a_t over all joints (``copy_errors``)."""
    return int(np.argmin(copy_errors(states, actions, episodes, columns, longest)))


def joint_copy_lags(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, columns: list[int], longest: int = 10
) -> list[int]:
    """Each joint's own k at which s_{t+k} best matches a_t: how long its follower takes to reach its leader."""
    return np.argmin(joint_copy_errors(states, actions, episodes, columns, longest), axis=0).tolist()


def resemblance(states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, longest: int = 10) -> np.ndarray:
    """(longest + 1, actions, states): |correlation| between a_t and s_{t+k} over the frames whose t+k lies in their
    episode (0 for a column that does not move)."""
    result = np.zeros((longest + 1, actions.shape[1], states.shape[1]))
    for k in range(longest + 1):
        rows = _lagged_pairs(episodes, k)
        if len(rows) < 3:
            continue
        a, s = actions[rows], states[rows + k]
        a, s = a - a.mean(axis=0), s - s.mean(axis=0)
        norms = np.linalg.norm(a, axis=0)[:, None] * np.linalg.norm(s, axis=0)[None, :]
        result[k] = np.abs(a.T @ s) / np.maximum(norms, 1e-12) * (norms > 1e-9)
    return result


def action_sources(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, named: list[int | None], longest: int = 10
) -> tuple[list[int], list[int]] | None:
    """Each action dimension's source column and lag: the state of the same name at its best copy lag, else the
    (column, lag) of largest |correlation|. None unless most dimensions are read off the state (named, or resembling
    a column: ``RESEMBLANCE``): actions that are not (an engine's thrust, an end-effector delta) keep the IDM of the
    whole observation. A dimension that resembles no column beside a majority that do (a waist among arm joints)
    still gets its closest column; its fit over every column can then win (``fit_linear``)."""
    states, actions = np.asarray(states, np.float64), np.asarray(actions, np.float64)
    columns, lags = list(named), [0] * len(named)
    same = [j for j, column in enumerate(named) if column is not None]
    if same:
        errors = joint_copy_errors(states, actions[:, same], episodes, [named[j] for j in same], longest)
        for j, lag in zip(same, np.argmin(errors, axis=0).tolist(), strict=True):
            lags[j] = lag
    other = [j for j, column in enumerate(named) if column is None]
    weak = 0
    if other:
        correlation = resemblance(states, actions[:, other], episodes, longest)
        for n, j in enumerate(other):
            lag, column = np.unravel_index(np.argmax(correlation[:, n]), correlation[:, n].shape)
            weak += int(correlation[lag, n, column] < RESEMBLANCE)
            columns[j], lags[j] = int(column), int(lag)
    if 2 * weak >= len(named):
        return None
    return columns, lags


def _fold_sums(
    features: np.ndarray, mean: np.ndarray, std: np.ndarray, targets: np.ndarray, folds: np.ndarray
) -> list[tuple]:
    """Per fold, (ZᵀZ, Zᵀy, Σy²) of its standardised features Z (with a column of ones): one fold standardised at a
    time, so that no standardised copy of all the features is held."""
    sums = []
    for fold in (folds == f for f in np.unique(folds)):
        scaled = np.concatenate([(features[fold] - mean) / std, np.ones((int(fold.sum()), 1))], axis=1)
        sums.append((scaled.T @ scaled, scaled.T @ targets[fold], (targets[fold] ** 2).sum(axis=0)))
    return sums


def _held_out_errors(sums: list[tuple], alphas: tuple[float, ...], penalty: np.ndarray) -> np.ndarray:
    """(alphas, targets): squared error of each fold's predictions by the fit on the other folds."""
    gram, moment = sum(g for g, _, _ in sums), sum(m for _, m, _ in sums)
    errors = np.zeros((len(alphas), moment.shape[1]))
    for n, alpha in enumerate(alphas):
        for fold_gram, fold_moment, fold_square in sums:
            coef = np.linalg.solve(gram - fold_gram + alpha * penalty, moment - fold_moment)
            predicted_square = (coef * (fold_gram @ coef)).sum(axis=0)
            errors[n] += fold_square - 2.0 * (coef * fold_moment).sum(axis=0) + predicted_square
    return errors


def fit_ridge(
    features: np.ndarray,
    targets: np.ndarray,
    groups: np.ndarray,
    alphas: tuple[float, ...] = RIDGE_ALPHAS,
    folds: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Ridge regression targets ≈ features @ W + b on standardised features (the intercept not penalised), the
    strength of each target column chosen from ``alphas`` by the squared error of its held-out predictions. The
    folds: ``folds`` (a fold number per frame) where given, else each episode (``groups``, in frame order) cut into
    ``BLOCKS`` contiguous blocks, one block left out at a time (over ``MAX_FOLDS`` blocks, that many folds of them).
    Each fold is solved from per-fold sums (ZᵀZ, Zᵀy), so the cost does not grow with folds × frames. Returns W and
    b in the features' own units, the alphas and their held-out squared errors."""
    features, targets = np.asarray(features, np.float64), np.asarray(targets, np.float64)
    mean, std = features.mean(axis=0), features.std(axis=0) + 1e-6
    penalty = np.diag(np.r_[np.ones(features.shape[1]), 0.0])
    sums = _fold_sums(features, mean, std, targets, episode_blocks(groups) % MAX_FOLDS if folds is None else folds)
    errors = _held_out_errors(sums, alphas, penalty)
    chosen = errors.argmin(axis=0)
    gram, moment = sum(g for g, _, _ in sums), sum(m for _, m, _ in sums)
    coef = np.zeros((features.shape[1] + 1, targets.shape[1]))
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


def selection_folds(groups: np.ndarray) -> np.ndarray:
    """The folds that choose between candidate fits: whole episodes (up to ``MAX_FOLDS``) where there are two or
    more, which is what a new episode asks of a fit (another pose of a joint that barely moved); blocks otherwise."""
    episodes, index = np.unique(groups, return_inverse=True)
    return index.reshape(-1) % MAX_FOLDS if len(episodes) >= 2 else episode_blocks(groups) % MAX_FOLDS


def gate_weights(residual: np.ndarray, correction: np.ndarray) -> np.ndarray:
    """Per joint, the share w ∈ [0, 1] of the network's ``correction`` that minimises the squared error of
    ``residual − w · correction`` (what the linear part leaves, on frames the network did not train on)."""
    fit = (residual * correction).sum(axis=0) / np.maximum((correction**2).sum(axis=0), 1e-12)
    return np.clip(fit, 0.0, 1.0)


def copy_map(
    flat: np.ndarray, actions: np.ndarray, state_dim: int, frames: list[int], columns: list[int], named: list[bool]
) -> np.ndarray:
    """(features, joints): the copy of each joint's source column at its window frame (``frames``) as a linear map of
    the flattened windows ``flat`` (N, frames × ``state_dim``): gain 1 for a joint of the same name, the
    least-squares slope otherwise (another arm's joint: its own scale and sign; the offset goes to the bias)."""
    copy = np.zeros((flat.shape[1], len(columns)))
    for j, (frame, column) in enumerate(zip(frames, columns, strict=True)):
        feature = frame * state_dim + column
        gain = 1.0
        if not named[j]:
            source = flat[:, feature] - flat[:, feature].mean()
            gain = float(source @ (actions[:, j] - actions[:, j].mean()) / max(source @ source, 1e-12))
        copy[feature, j] = gain
    return copy


def fit_linear(
    windows: np.ndarray,
    actions: np.ndarray,
    episodes: np.ndarray,
    frames: list[int],
    columns: list[int],
    named: list[bool],
) -> tuple[np.ndarray, np.ndarray, dict[str, list]]:
    """The linear part a ≈ flat(window) @ W + b from labelled windows (N, F, D) and actions (N, A): the copy
    (``copy_map``) plus, per joint, a ridge correction shrunk toward it, over the joint's own source column at every
    frame of the window, or over every column where that predicts held-out episodes clearly better
    (``CLEARLY_BETTER``, ``selection_folds``). Returns W, b and per joint the fit taken ("own" or "all"), its
    strength and both candidates' held-out squared errors."""
    count, window_frames, state_dim = windows.shape
    flat = windows.reshape(count, -1).astype(np.float64)
    actions = np.asarray(actions, np.float64)
    copy = copy_map(flat, actions, state_dim, frames, columns, named)
    residual = actions - flat @ copy
    folds = selection_folds(episodes)
    all_weight, all_bias, all_alpha, all_error = fit_ridge(flat, residual, episodes, folds=folds)
    weight, bias = copy.copy(), np.zeros(actions.shape[1])
    taken, alphas, own_errors = [], [], []
    for j, column in enumerate(columns):
        own = np.arange(window_frames) * state_dim + column
        own_weight, own_bias, own_alpha, own_error = fit_ridge(flat[:, own], residual[:, [j]], episodes, folds=folds)
        own_errors.append(float(own_error[0]))
        if all_error[j] < CLEARLY_BETTER * own_error[0]:
            weight[:, j] += all_weight[:, j]
            bias[j], alpha, fit = all_bias[j], all_alpha[j], "all"
        else:
            weight[own, j] += own_weight[:, 0]
            bias[j], alpha, fit = own_bias[0], own_alpha[0], "own"
        taken.append(fit)
        alphas.append(float(alpha))
    report = {"fit": taken, "ridge_alpha": alphas, "own_error": own_errors, "all_error": all_error.tolist()}
    return weight, bias, report


class JointIDM(nn.Module):
    """a_t from the window of joint states (B, F, D) at the config's offsets (raw units): the linear part (the copy of
    each joint's source at its lag plus a ridge correction; buffers, fitted once by ``fit``) plus the gated per-joint
    network; ``forward`` returns the network's per-joint correction (B, A), which the IDM head turns into the
    action's scaled units; ``prior`` is the linear part in raw units."""

    def __init__(self, offsets: list[int], lags: list[int], columns: list[int], state_dim: int, hidden: int):
        super().__init__()
        frames, joints = len(offsets), len(columns)
        self.copy_frames = [offsets.index(lag) for lag in lags]
        self.register_buffer("columns", torch.as_tensor(columns, dtype=torch.long), persistent=False)
        features = frames * state_dim
        # "linear_*", not the "weight"/"bias" of checkpoints whose linear part left the copy out: those must not load.
        for name, shape in (("linear_weight", (features, joints)), ("reference_weight", (features, joints))):
            self.register_buffer(name, torch.zeros(shape))
        for name in ("linear_bias", "reference_bias", "gate"):
            self.register_buffer(name, torch.zeros(joints))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        # The joints' mean and spread (the network reads standardised windows) and the standardised range the network
        # saw: a pose outside it is clamped to its edge, so that a joint that barely moved in the labelled episodes
        # cannot send the network far outside what it learned.
        self.register_buffer("center", torch.zeros(state_dim))
        self.register_buffer("scale", torch.ones(state_dim))
        self.register_buffer("low", torch.full((state_dim,), -1e6))
        self.register_buffer("high", torch.full((state_dim,), 1e6))
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
        """The linear part (B, A), raw action units: copy plus ridge correction."""
        return window.float().flatten(1) @ self.linear_weight + self.linear_bias

    def reference(self, window: Tensor) -> Tensor:
        """The plain ridge regression on the same window (B, A): the simplest fit, reported beside the model."""
        return window.float().flatten(1) @ self.reference_weight + self.reference_bias

    def forward(self, window: Tensor) -> Tensor:
        """The network's per-joint correction (B, A): each joint reads its own source's window, standardised."""
        standard = (window.float() - self.center) / self.scale
        own = standard.clamp(self.low, self.high)[:, :, self.columns]
        return self.net(own.transpose(1, 2).reshape(len(own), -1, 1)).squeeze(-1)

    def fit(self, windows: np.ndarray, actions: np.ndarray, episodes: np.ndarray, named: list[bool]) -> dict[str, list]:
        """The linear parts in closed form from labelled windows (N, F, D) and actions (N, A) (``fit_linear``;
        ``named``: whether each joint's source is the state of its own name), and the plain reference ridge on a_t
        (``REFERENCE_ALPHA``)."""
        columns = self.columns.cpu().numpy().tolist()
        weight, bias, report = fit_linear(windows, actions, episodes, self.copy_frames, columns, named)
        flat = windows.reshape(len(windows), -1)  # fit_ridge reads it in float64
        reference_weight, reference_bias, *_ = fit_ridge(flat, actions, episodes, (REFERENCE_ALPHA,))
        device = self.linear_weight.device
        as_buffer = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)  # noqa: E731
        self.linear_weight.copy_(as_buffer(weight))
        self.linear_bias.copy_(as_buffer(bias))
        self.reference_weight.copy_(as_buffer(reference_weight))
        self.reference_bias.copy_(as_buffer(reference_bias))
        values = windows.reshape(-1, windows.shape[-1]).astype(np.float64)
        center, scale = values.mean(axis=0), values.std(axis=0) + 1e-3
        self.center.copy_(as_buffer(center))
        self.scale.copy_(as_buffer(scale))
        self.low.copy_(as_buffer((values.min(axis=0) - center) / scale))
        self.high.copy_(as_buffer((values.max(axis=0) - center) / scale))
        self.fitted.fill_(True)
        return report
