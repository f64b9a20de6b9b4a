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
same window (``reference``) is kept beside it as the simplest fit that relabelling reports.

A source has a *kind* (``SOURCE_KINDS``): a position a_t ≈ g·s_{t+lag} + b (an arm's leader), a *difference*
a_t ≈ g·(s_{t+lag+1} − s_{t+lag}) + b (measured joint velocities, end-effector deltas), or *camera*: no state column
follows the dimension (a gripper commanded from a keyboard whose opening no column records), so a camera network
labels it and its linear part is the ridge over every column. Each dimension takes the kind that follows it more
closely on the labelled frames (``action_sources``). A dimension that barely moved in the labelled episodes
(``idle_dimensions``) keeps the bare copy of its source (gain 1 for a namesake's position, the gain of the other
differences for a difference) with no correction, so that a new episode that moves it is not extrapolated."""

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
POSITION, DIFFERENCE, CAMERA = "position", "difference", "camera"
SOURCE_KINDS = (POSITION, DIFFERENCE, CAMERA)
# Name endings of a rate or a delta of a state column (``joint_0_vel`` is the rate of ``joint_0``) and of a position.
RATE_SUFFIXES = ("_vel", ".vel", "_velocity", ".velocity", "_delta", ".delta", "_dot")
POSITION_SUFFIXES = ("_pos", ".pos", "_position", ".position")
# A dimension is idle in the labelled episodes when its actions' spread is below this share of the median spread of
# all dimensions (a humanoid's resting arm: 0.005–0.02 rad against 0.07–0.1 where it moves).
IDLE_SHARE = 0.1


def named_sources(action_names: list[str] | None, state_names: list[str] | None) -> list[int | None]:
    """For each action dimension, the state column of the same name, or None."""
    position = {name: i for i, name in enumerate(state_names or [])}
    return [position.get(name) for name in action_names or []]


def name_stem(name: str) -> str:
    """A column's name without the ending that says what of it is recorded (``joint_0_vel``, ``joint_0.pos`` →
    ``joint_0``)."""
    for suffix in RATE_SUFFIXES + POSITION_SUFFIXES:
        if name.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def stem_sources(action_names: list[str] | None, state_names: list[str] | None) -> list[int | None]:
    """For each action dimension, the one state column whose name has the same stem (``name_stem``), or None."""
    stems: dict[str, list[int]] = {}
    for i, name in enumerate(state_names or []):
        stems.setdefault(name_stem(name), []).append(i)
    matches = [stems.get(name_stem(name), []) for name in action_names or []]
    return [match[0] if len(match) == 1 else None for match in matches]


def is_rate_name(name: str) -> bool:
    """Whether an action's name says it is a rate or a delta (``RATE_SUFFIXES``)."""
    return name.endswith(RATE_SUFFIXES)


def idle_dimensions(actions: np.ndarray) -> np.ndarray:
    """Per action dimension, whether it barely moved in these (labelled) frames: its spread below ``IDLE_SHARE`` of
    the median spread of all dimensions (never with fewer than three dimensions: no median to judge by)."""
    spread = np.asarray(actions, np.float64).std(axis=0)
    if len(spread) < 3:
        return np.zeros(len(spread), dtype=bool)
    return spread < IDLE_SHARE * np.median(spread)


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


def rows_within(episodes: np.ndarray, offsets: tuple[int, ...]) -> np.ndarray:
    """Rows t whose t + offset lies in t's episode for every offset."""
    count = len(episodes)
    t = np.arange(count)
    inside = np.ones(count, dtype=bool)
    for offset in offsets:
        other = t + offset
        fits = (other >= 0) & (other < count)
        inside &= fits
        inside[fits] &= episodes[other[fits]] == episodes[fits]
    return np.flatnonzero(inside)


def _abs_correlation(a: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(A, S) |correlation| between the columns of ``a`` and of ``s`` (0 for a column that does not move)."""
    a, s = a - a.mean(axis=0), s - s.mean(axis=0)
    norms = np.linalg.norm(a, axis=0)[:, None] * np.linalg.norm(s, axis=0)[None, :]
    return np.abs(a.T @ s) / np.maximum(norms, 1e-12) * (norms > 1e-9)


def resemblance(states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, longest: int = 10) -> np.ndarray:
    """(longest + 1, actions, states): |correlation| between a_t and s_{t+k} over the frames whose t+k lies in their
    episode (0 for a column that does not move)."""
    result = np.zeros((longest + 1, actions.shape[1], states.shape[1]))
    for k in range(longest + 1):
        rows = _lagged_pairs(episodes, k)
        if len(rows) >= 3:
            result[k] = _abs_correlation(actions[rows], states[rows + k])
    return result


def difference_resemblance(
    states: np.ndarray, actions: np.ndarray, episodes: np.ndarray, lowest: int, longest: int
) -> np.ndarray:
    """(longest − lowest, actions, states): |correlation| between a_t and s_{t+d+1} − s_{t+d} for d = lowest …
    longest − 1, over the frames whose t+d and t+d+1 lie in their episode."""
    result = np.zeros((longest - lowest, actions.shape[1], states.shape[1]))
    for n, d in enumerate(range(lowest, longest)):
        rows = rows_within(episodes, (d, d + 1))
        if len(rows) >= 3:
            result[n] = _abs_correlation(actions[rows], states[rows + d + 1] - states[rows + d])
    return result


def _best(correlation: np.ndarray, columns: list[int] | None) -> tuple[float, int, int]:
    """(|correlation|, lag index, column) of the largest entry of ``correlation`` (lags, states), over ``columns``
    (all where None)."""
    if columns is not None:
        masked = np.full_like(correlation, -1.0)
        masked[:, columns] = correlation[:, columns]
        correlation = masked
    lag, column = np.unravel_index(np.argmax(correlation), correlation.shape)
    return float(correlation[lag, column]), int(lag), int(column)


def action_sources(
    states: np.ndarray,
    actions: np.ndarray,
    episodes: np.ndarray,
    named: list[int | None],
    longest: int = 10,
    stems: list[int | None] | None = None,
    rate_names: list[bool] | None = None,
    lowest: int = 0,
    cameras: bool = False,
) -> tuple[list[int], list[int], list[str]] | None:
    """Each action dimension's source column, lag and kind (``SOURCE_KINDS``), from the labelled frames.

    A dimension named as a state column (``named``) copies that column's position at its best copy lag (the least
    mean absolute difference), unless its position follows it less than ``RESEMBLANCE`` and its difference does.
    Another takes, among the column of the same stem (``stems``: ``joint_0_vel`` → ``joint_0``) or else every
    column, the position a_t ~ s_{t+k} (k = 0 … ``longest``) or difference a_t ~ s_{t+d+1} − s_{t+d}
    (d = ``lowest`` … ``longest`` − 1) of largest |correlation|. One that follows none at ``RESEMBLANCE`` is read off
    the cameras where the IDM has some (``cameras``), else keeps its closest source. A dimension idle in the labelled
    frames (``idle_dimensions``) whose name ties it to a column keeps that column, as a difference where its name says
    it is a rate (``rate_names``, then at the median lag of the other differences: its own fits noise). None where no
    dimension follows the state (with cameras) or most do not (without): such actions (an engine's thrust) keep the
    IDM of the whole observation."""
    states, actions = np.asarray(states, np.float64), np.asarray(actions, np.float64)
    count = len(named)
    stems = stems or [None] * count
    rate_names = rate_names or [False] * count
    positions = resemblance(states, actions, episodes, longest)
    differences = difference_resemblance(states, actions, episodes, lowest, longest)
    copy_lags = {}
    same = [j for j, column in enumerate(named) if column is not None]
    if same:
        errors = joint_copy_errors(states, actions[:, same], episodes, [named[j] for j in same], longest)
        copy_lags = dict(zip(same, np.argmin(errors, axis=0).tolist(), strict=True))
    idle = idle_dimensions(actions)
    columns, lags, kinds, strong = [0] * count, [0] * count, [POSITION] * count, [False] * count
    for j in range(count):
        own = named[j] if named[j] is not None else stems[j]
        candidates = None if own is None else [own]
        position = _best(positions[:, j], candidates)
        difference = _best(differences[:, j], candidates) if len(differences) else (-1.0, 0, 0)
        if named[j] is not None and not (position[0] < RESEMBLANCE <= difference[0]):
            columns[j], lags[j], kinds[j] = named[j], copy_lags[j], POSITION
            strong[j] = True
            continue
        if position[0] >= difference[0]:
            strength, (_, lag, column), kind = position[0], position, POSITION
        else:
            strength, (_, lag, column), kind = difference[0], difference, DIFFERENCE
            lag += lowest
        columns[j], lags[j], kinds[j] = column, lag, kind
        strong[j] = strength >= RESEMBLANCE or (idle[j] and own is not None)
        if idle[j] and own is not None:
            columns[j], kinds[j] = own, DIFFERENCE if rate_names[j] else POSITION
    for j in np.flatnonzero(idle & np.array(strong)):  # an idle difference's lag is the others' usual one
        usual = [lags[i] for i in range(count) if kinds[i] == DIFFERENCE and strong[i] and not idle[i]]
        if kinds[j] != DIFFERENCE:
            continue
        if usual:
            lags[j] = int(np.median(usual))
    weak = count - sum(strong)
    if (cameras and weak == count) or (not cameras and 2 * weak >= count):
        return None
    if cameras:  # a camera dimension's column feeds its ridge and network only; its lag is the camera network's
        kinds = [kind if is_strong else CAMERA for kind, is_strong in zip(kinds, strong, strict=True)]
        lags = [lag if is_strong else 0 for lag, is_strong in zip(lags, strong, strict=True)]
    return columns, lags, kinds


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
    (``CLEARLY_BETTER``, ``selection_folds``); a camera dimension takes the fit over every column, an idle one
    (``idle_dimensions``) none. Returns W, b and per dimension the fit taken ("own", "all" or "copy"), its strength
    and both candidates' held-out squared errors."""
    count, window_frames, state_dim = windows.shape
    flat = windows.reshape(count, -1).astype(np.float64)
    actions = np.asarray(actions, np.float64)
    columns, _, kinds = sources
    idle = idle_dimensions(actions)
    copy = copy_map(flat, actions, state_dim, offsets, sources, named, idle)
    residual = actions - flat @ copy
    folds = selection_folds(episodes)
    all_weight, all_bias, all_alpha, all_error = fit_ridge(flat, residual, episodes, folds=folds)
    weight, bias = copy.copy(), np.zeros(actions.shape[1])
    taken, alphas, own_errors = [], [], []
    for j, column in enumerate(columns):
        own = np.arange(window_frames) * state_dim + column
        own_weight, own_bias, own_alpha, own_error = fit_ridge(flat[:, own], residual[:, [j]], episodes, folds=folds)
        own_errors.append(float(own_error[0]))
        if idle[j] and kinds[j] != CAMERA:  # no correction to extrapolate where a new episode moves it
            bias[j], alpha, fit = residual[:, j].mean(), 0.0, "copy"
        elif kinds[j] == CAMERA or all_error[j] < CLEARLY_BETTER * own_error[0]:
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
