"""Which state column, lag and kind each action dimension of the linear-first IDM (``joint_idm``) reads, chosen from
the labelled frames: a position a_t ~ s_{t+lag}, a difference a_t ~ s_{t+lag+1} − s_{t+lag}, or a camera where no
column follows it (``action_sources``); names tie a dimension to a column (same name, or same stem); a dimension that
barely moved in the labelled frames is idle (``idle_dimensions``)."""

from __future__ import annotations

import math

import numpy as np

# The longest lag searched and the window's reach: 0.35 s, well past the delays measured on real arms (about 0.13 s on
# an SO-101, up to 0.33 s on a humanoid's fingers); 10 frames at least.
MAX_LAG_SECONDS = 0.35
# A differently-named action dimension follows a state column when their |correlation| (at the best lag) reaches this.
RESEMBLANCE = 0.8
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
    """Per action dimension (or state column), whether it barely moved in these (labelled) frames: its spread below
    ``IDLE_SHARE`` of the median spread of the dimensions that moved at all, so that columns that never move (an
    environment state's padding: 16 of Meta-World's 43) do not pull the median down to the barely moving ones (never
    with fewer than three dimensions: no median to judge by)."""
    spread = np.asarray(actions, np.float64).std(axis=0)
    moved = spread[spread > 0]
    if len(spread) < 3 or not len(moved):
        return np.zeros(len(spread), dtype=bool)
    return spread < IDLE_SHARE * np.median(moved)


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
    Another takes, among the column of the same stem (``stems``: ``joint_0_vel`` → ``joint_0``) or else every column
    that moved in the labelled frames, the position a_t ~ s_{t+k} (k = 0 … ``longest``) or difference a_t ~
    s_{t+d+1} − s_{t+d} (d = ``lowest`` … ``longest`` − 1) of largest |correlation|. One that follows none at
    ``RESEMBLANCE`` is read off the cameras where the IDM has some (``cameras``), else keeps its closest source. A
    dimension idle in the labelled frames (``idle_dimensions``) whose name ties it to a column keeps that column, as
    a difference where its name says it is a rate (``rate_names``, then at the median lag of the other differences:
    its own fits noise). None where no dimension follows the state (with cameras) or most do not (without): such
    actions (an engine's thrust) keep the IDM of the whole observation."""
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
    # A column that barely moved in the labelled frames follows anything by chance, and a new episode that moves it
    # would move the labels of what chose it: no dimension without a name chooses it.
    moving = np.flatnonzero(~idle_dimensions(states)).tolist()
    columns, lags, kinds, strong = [0] * count, [0] * count, [POSITION] * count, [False] * count
    for j in range(count):
        own = named[j] if named[j] is not None else stems[j]
        candidates = moving if own is None else [own]
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
