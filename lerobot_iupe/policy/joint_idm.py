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
(physically grounded) or a ridge over that and the central frames of every vector column that moved in the labelled
frames (the state and any other vector key the model reads, such as the environment state that shows the puck a hand
pushes; a column that barely moved would be extrapolated where a new episode moves it). The second is taken only
where it predicts held-out *episodes* clearly better (``CLEARLY_BETTER``): on a new episode a joint that barely
moved in the labelled ones still follows its own state, and a fit over many columns from few episodes extrapolates
worse (on a real humanoid, a ridge over all 26 joints scored R² 0.852 where each joint's own window scored 0.980). A
plain ridge on the same window (``reference``) is kept beside it as the simplest fit that relabelling reports.

A source has a *kind* (``SOURCE_KINDS``): a position a_t ≈ g·s_{t+lag} + b (an arm's leader), a *difference* a_t ≈
g·(s_{t+lag+1} − s_{t+lag}) + b (measured joint velocities, end-effector deltas), or *camera*: no state column follows
the dimension (a gripper commanded from a keyboard whose opening no column records), so a camera network labels it from
its labelled mean: a ridge over every column extrapolated without bound where a joint that barely moved in 2 labelled
episodes moved in a new one (the generator's velocity arm: the gripper at R² −7,511). Each dimension takes the kind that
follows it more closely on the labelled frames (``action_sources``). A dimension that barely moved in the labelled
episodes (``idle_dimensions``) keeps the bare copy of its source (gain 1 for a namesake's position) with no
correction, so that a new episode that moves it is not extrapolated; an idle difference borrows the filter the other
differences fitted over their own windows (their median, made to sum to 0, at the others' median gain): on the
generator's velocity arm with 2 labelled episodes its joint_4 went from R² 0.774 (the bare difference) to 0.895."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_iupe.policy.action_sources import CAMERA, DIFFERENCE, POSITION, RESEMBLANCE, idle_dimensions

RIDGE_ALPHAS = tuple(10.0**p for p in range(-3, 6))
MAX_FOLDS = 20
BLOCKS = 10
# The reference a user would fit first: a ridge regression with scikit-learn's default strength, standardised inputs.
REFERENCE_ALPHA = 1.0
# Share of each labelled episode, at its end, on which the network's gate is judged (it never trains on them).
GATE_SHARE = 0.2
# The fit over every column replaces the joint's own window only where its held-out error is below this share of it.
CLEARLY_BETTER = 0.8


class FoldSums(NamedTuple):
    """Per fold, the sums a ridge regression's held-out errors are solved from: (ZᵀZ, Zᵀy, Σy²) of the standardised
    features Z (with a last column of ones) and the targets y, and the standardisation (``mean``, ``std``)."""

    mean: np.ndarray
    std: np.ndarray
    grams: list[np.ndarray]
    moments: list[np.ndarray]
    squares: list[np.ndarray]


def fold_sums(features: np.ndarray, targets: np.ndarray, folds: np.ndarray) -> FoldSums:
    """``FoldSums`` of ``features`` (N, P) and ``targets`` (N, T) over ``folds`` (a fold number per row): one fold
    standardised at a time, so that no standardised copy of all the features is held."""
    features, targets = np.asarray(features, np.float64), np.asarray(targets, np.float64)
    mean, std = features.mean(axis=0), features.std(axis=0) + 1e-6
    sums = FoldSums(mean, std, [], [], [])
    for fold in (folds == f for f in np.unique(folds)):
        scaled = np.concatenate([(features[fold] - mean) / std, np.ones((int(fold.sum()), 1))], axis=1)
        sums.grams.append(scaled.T @ scaled)
        sums.moments.append(scaled.T @ targets[fold])
        sums.squares.append((targets[fold] ** 2).sum(axis=0))
    return sums


def solve_ridge(
    sums: FoldSums,
    alphas: tuple[float, ...] = RIDGE_ALPHAS,
    columns: np.ndarray | None = None,
    targets: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``fit_ridge`` from its ``FoldSums``, on a subset of their feature ``columns`` and ``targets`` (all by default):
    each subset is a sub-block of the sums, so many candidate fits over one set of features read them once."""
    size = len(sums.mean)
    columns = np.arange(size) if columns is None else np.asarray(columns)
    targets = np.arange(sums.moments[0].shape[1]) if targets is None else np.asarray(targets)
    block = np.r_[columns, size]  # the intercept's column of ones is the last
    grams = [g[np.ix_(block, block)] for g in sums.grams]
    moments = [m[np.ix_(block, targets)] for m in sums.moments]
    squares = [q[targets] for q in sums.squares]
    penalty = np.diag(np.r_[np.ones(len(columns)), 0.0])
    gram, moment = sum(grams), sum(moments)
    errors = np.zeros((len(alphas), len(targets)))
    for n, alpha in enumerate(alphas):
        for fold_gram, fold_moment, fold_square in zip(grams, moments, squares, strict=True):
            coef = np.linalg.solve(gram - fold_gram + alpha * penalty, moment - fold_moment)
            predicted_square = (coef * (fold_gram @ coef)).sum(axis=0)
            errors[n] += fold_square - 2.0 * (coef * fold_moment).sum(axis=0) + predicted_square
    chosen = errors.argmin(axis=0)
    coef = np.zeros((len(columns) + 1, len(targets)))
    for n in np.unique(chosen):
        coef[:, chosen == n] = np.linalg.solve(gram + alphas[n] * penalty, moment[:, chosen == n])
    weight = coef[:-1] / sums.std[columns, None]
    held_out = errors[chosen, np.arange(len(targets))]
    return weight, coef[-1] - sums.mean[columns] @ weight, np.asarray(alphas)[chosen], held_out


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
    targets = np.asarray(targets, np.float64)
    folds = episode_blocks(groups) % MAX_FOLDS if folds is None else folds
    return solve_ridge(fold_sums(features, targets, folds), alphas)


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


def source_features(offsets: list[int], lag: int, column: int, kind: str, state_dim: int) -> dict[int, float]:
    """The flattened window's features (index: coefficient) whose sum is a dimension's source: s_{t+lag} of
    ``column`` for a position, s_{t+lag+1} − s_{t+lag} for a difference, none for a camera dimension."""
    if kind == POSITION:
        return {offsets.index(lag) * state_dim + column: 1.0}
    if kind == DIFFERENCE:
        return {offsets.index(lag + 1) * state_dim + column: 1.0, offsets.index(lag) * state_dim + column: -1.0}
    return {}


def copy_map(
    flat: np.ndarray,
    actions: np.ndarray,
    state_dim: int,
    offsets: list[int],
    sources: tuple[list[int], list[int], list[str]],
    named: list[bool],
    idle: np.ndarray | None = None,
) -> np.ndarray:
    """(features, dimensions): the copy of each dimension's source (``source_features``; ``sources``: columns, lags,
    kinds) as a linear map of the flattened windows ``flat`` (N, frames × ``state_dim``): gain 1 for a position of
    the same name, the least-squares slope otherwise (another arm's joint, a velocity's 1/Δt: their own scale and
    sign; the offset goes to the bias), and for an ``idle`` difference the median gain of the others (its own slope
    fits noise)."""
    columns, lags, kinds = sources
    idle = np.zeros(len(columns), dtype=bool) if idle is None else idle
    base = np.zeros((flat.shape[1], len(columns)))
    for j, (column, lag, kind) in enumerate(zip(columns, lags, kinds, strict=True)):
        for feature, sign in source_features(offsets, lag, column, kind, state_dim).items():
            base[feature, j] = sign
    gains = np.ones(len(columns))
    for j in range(len(columns)):
        if kinds[j] != CAMERA and not (named[j] and kinds[j] == POSITION):
            source = flat @ base[:, j]
            source = source - source.mean()
            gains[j] = float(source @ (actions[:, j] - actions[:, j].mean()) / max(source @ source, 1e-12))
    moving = [j for j in range(len(columns)) if kinds[j] == DIFFERENCE and not idle[j]]
    if moving:
        gains[[j for j in range(len(columns)) if kinds[j] == DIFFERENCE and idle[j]]] = np.median(gains[moving])
    return base * gains


def fit_linear(
    windows: np.ndarray,
    actions: np.ndarray,
    episodes: np.ndarray,
    offsets: list[int],
    sources: tuple[list[int], list[int], list[str]],
    named: list[bool],
) -> tuple[np.ndarray, np.ndarray, dict[str, list]]:
    """The linear part a ≈ flat(window) @ W + b from labelled windows (N, F, D) at ``offsets`` and actions (N, A):
    the copy (``copy_map``) plus, per dimension, a ridge correction shrunk toward it, over its own source column at
    every frame of the window, or over every column where that predicts held-out episodes clearly better
    (``CLEARLY_BETTER``, ``selection_folds``); an idle one (``idle_dimensions``) none, a camera dimension only its
    labelled mean, an idle difference the other differences' filter (``borrowed_filter``). Returns W, b and per
    dimension the fit taken ("own", "all", "copy", "borrowed" or "mean"), its strength and both candidates' held-out
    squared errors."""
    count, window_frames, state_dim = windows.shape
    flat = windows.reshape(count, -1).astype(np.float64)
    actions = np.asarray(actions, np.float64)
    columns, _, kinds = sources
    idle = idle_dimensions(actions)
    copy = copy_map(flat, actions, state_dim, offsets, sources, named, idle)
    residual = actions - flat @ copy
    followed = 1.0 - residual.var(axis=0) / np.maximum(actions.var(axis=0), 1e-12) >= RESEMBLANCE**2
    folds = selection_folds(episodes)
    # Every column is read over the window's central frames −k … k+1 only (k = −offsets[0]), as the IDM of vectors
    # reads them: over the whole window, 43 columns × 37 frames of Meta-World push, the fit over 616 labelled frames
    # labelled held-out episodes' dz at R² 0.956 against 0.975.
    central = [f for f, offset in enumerate(offsets) if offset <= 1 - offsets[0]]
    # A column that barely moved in the labelled frames (``idle_dimensions``, as the source search skips it) is left
    # out: standardised, its noise is a feature whose effect was never seen, and a new episode that moves it
    # extrapolates (Meta-World peg-insert-side: the peg's tilt, spread 1e-5 in 10 labelled episodes, sent a held-out
    # episode's dz labels to R² −3.76 over 40 of them).
    moving = np.flatnonzero(~idle_dimensions(windows.reshape(-1, state_dim)))
    every_column = np.array([f * state_dim + c for f in central for c in moving], dtype=np.int64)
    weight, bias = copy.copy(), np.zeros(actions.shape[1])
    owns = [np.arange(window_frames) * state_dim + column for column in columns]
    read = np.union1d(every_column, np.concatenate(owns)).astype(np.int64)  # every feature some candidate reads
    sums = fold_sums(flat[:, read], residual, folds)  # once: 26 joints' candidates over 100k frames took 5× longer
    position = np.full(flat.shape[1], -1)
    position[read] = np.arange(len(read))
    taken, alphas, own_errors, all_errors = [], [], [], []
    for j, own in enumerate(owns):
        own_weight, own_bias, own_alpha, own_error = solve_ridge(sums, columns=position[own], targets=[j])
        wide = np.union1d(every_column, own)
        all_weight, all_bias, all_alpha, all_error = solve_ridge(sums, columns=position[wide], targets=[j])
        own_errors.append(float(own_error[0]))
        all_errors.append(float(all_error[0]))
        if kinds[j] == CAMERA:  # the camera network labels it from the labelled mean (see the module's docstring)
            bias[j], alpha, fit = residual[:, j].mean(), 0.0, "mean"
        elif idle[j]:  # no correction to extrapolate where a new episode moves it
            bias[j], alpha, fit = residual[:, j].mean(), 0.0, "copy"
        elif all_error[0] < CLEARLY_BETTER * own_error[0]:
            weight[wide, j] += all_weight[:, 0]
            bias[j], alpha, fit = all_bias[0], all_alpha[0], "all"
        else:
            weight[own, j] += own_weight[:, 0]
            bias[j], alpha, fit = own_bias[0], own_alpha[0], "own"
        taken.append(fit)
        alphas.append(float(alpha))
    for j in np.flatnonzero(idle & (np.asarray(kinds) == DIFFERENCE)):
        own = np.arange(window_frames) * state_dim + columns[j]
        shape = borrowed_filter(weight, copy, sources, offsets, state_dim, idle | ~followed, taken)
        if shape is not None:  # the other velocities' filter over their own window, at this one's gain
            weight[own, j] = shape * weight[offsets.index(sources[1][j] + 1) * state_dim + columns[j], j]
            bias[j], taken[j] = (actions[:, j] - flat[:, own] @ weight[own, j]).mean(), "borrowed"
    report = {"fit": taken, "ridge_alpha": alphas, "own_error": own_errors, "all_error": all_errors}
    return weight, bias, report


def borrowed_filter(
    weight: np.ndarray,
    copy: np.ndarray,
    sources: tuple[list[int], list[int], list[str]],
    offsets: list[int],
    state_dim: int,
    idle: np.ndarray,
    taken: list[str],
) -> np.ndarray | None:
    """The median, over the moving differences fitted on their own window (``idle`` marks those left out: idle, or
    not following their column at |correlation| ≥ ``RESEMBLANCE``), of their fitted weights over that window divided
    by their copy's gain: the filter (a centred difference, say, for a velocity measured at t) that an idle
    difference, whose own fit would be a fit to noise, borrows. None without such a difference."""
    columns, lags, kinds = sources
    shapes = []
    for k, column in enumerate(columns):
        if kinds[k] == DIFFERENCE and not idle[k] and taken[k] == "own":
            own = np.arange(len(offsets)) * state_dim + column
            gain = copy[offsets.index(lags[k] + 1) * state_dim + column, k]
            if gain != 0.0:
                shapes.append(weight[own, k] / gain)
    if not shapes:
        return None
    shape = np.median(shapes, axis=0)
    return shape - shape.mean()  # a filter of differences only: a pose never labelled cannot move the label


class JointIDM(nn.Module):
    """a_t from the window of joint states (B, F, D) at the config's offsets (raw units): the linear part (the copy of
    each joint's source at its lag plus a ridge correction; buffers, fitted once by ``fit``) plus the gated per-joint
    network; ``forward`` returns the network's per-joint correction (B, A), which the IDM head turns into the
    action's scaled units; ``prior`` is the linear part in raw units."""

    def __init__(
        self,
        offsets: list[int],
        lags: list[int],
        columns: list[int],
        state_dim: int,
        hidden: int,
        kinds: list[str] | None = None,
    ):
        super().__init__()
        frames, joints = len(offsets), len(columns)
        self.offsets, self.lags = list(offsets), list(lags)
        self.kinds = list(kinds or [POSITION] * joints)
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
        sources = (columns, self.lags, self.kinds)
        weight, bias, report = fit_linear(windows, actions, episodes, self.offsets, sources, named)
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
