"""The algorithmic core of IUPE as small pure functions: label/action choice, Eq. 1, the sampling rule, action
cells for continuous actions, metrics.

The sampling rule works on action *classes*: the action ids of a discrete space, or for a continuous (Box) space
the cells of a k-means partition fitted on the pre-demonstrations' actions (``ActionCells``)."""

from __future__ import annotations

import numpy as np
import torch

from lerobot_iupe.data.transitions import Transitions


def choose_actions(logits: torch.Tensor, explore: bool, generator: torch.Generator | None = None) -> torch.Tensor:
    """One action per row: a categorical draw from softmax(logits) when exploring, else the argmax."""
    if not explore:
        return logits.argmax(dim=-1)
    probs = torch.softmax(logits.float(), dim=-1)
    return torch.multinomial(probs, 1, generator=generator).squeeze(-1)


def frame_differences(values: torch.Tensor, reference: int, frames: list[int] | None = None) -> torch.Tensor:
    """The IDM's input [x_ref, x_j − x_ref for every other j] (B, len(frames), V) of ``values`` (B, F, V), ``frames``
    (default: all) in order and ``reference`` one of them, written once into a new contiguous tensor whatever the
    strides of ``values``: a gathered copy of the frames, their differences and the concatenation would each cost
    a pass over the frames (a camera network's input is 0.2 MB a window at 96×128)."""
    frames = list(range(values.shape[1])) if frames is None else frames
    out = torch.empty(len(values), len(frames), values.shape[-1], dtype=values.dtype, device=values.device)
    start = values[:, reference]
    out[:, 0] = start
    for n, j in enumerate(f for f in frames if f != reference):
        torch.sub(values[:, j], start, out=out[:, n + 1])
    return out


def success_action_distribution(episode_actions: list[np.ndarray], successes: np.ndarray, n_actions: int) -> np.ndarray:
    """Eq. 1: P(a|E) = (1/|E|) Σ_e v_e · freq_e(a). Sums to r, the success rate."""
    total = np.zeros(n_actions)
    for actions, success in zip(episode_actions, successes, strict=True):
        if success and len(actions):
            total += np.bincount(actions, minlength=n_actions) / len(actions)
    return total / max(len(episode_actions), 1)


def apportion(total: int, weights: np.ndarray, minimum_one: np.ndarray | None = None) -> np.ndarray:
    """Split ``total`` into integer counts ∝ ``weights`` (largest remainder). Where ``minimum_one`` is set, a
    positive-weight class that got none takes one from the largest class, when ``total`` allows it."""
    weights = np.asarray(weights, dtype=np.float64)
    counts = np.zeros(len(weights), dtype=np.int64)
    if total <= 0 or weights.sum() <= 0:
        return counts
    exact = weights / weights.sum() * total
    counts += np.floor(exact).astype(np.int64)
    order = np.argsort(-(exact - np.floor(exact)), kind="stable")
    counts[order[: total - counts.sum()]] += 1
    if minimum_one is not None:
        starved = np.flatnonzero(minimum_one & (weights > 0) & (counts == 0))
        if len(starved) + np.count_nonzero(counts) <= total:
            for cls in starved:
                counts[np.argmax(counts)] -= 1
                counts[cls] = 1
    return counts


def sampling_counts(
    p_success: np.ndarray, pre_counts: np.ndarray, size: int, max_success_share: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """How many transitions per action to take from successful runs and from pre-demonstrations.

    With r = Σ P(a|E): share r of ``size`` from successful runs, per action ∝ P(a|E); share 1 − r from
    pre-demonstrations, per action ∝ n_pre(a) · (1 − P(a|E)) ("inverse probability" applied to I_pre's own action
    frequencies, so that r = 0 gives I_pre's distribution — I_pre itself at size |I_pre| — also when I_pre is not
    balanced; on a balanced I_pre this is the paper's ∝ 1 − P(a|E)). Every action present in I_pre is kept (at
    least one sample) while r < 1. Where r exceeds ``max_success_share``, P(a|E) is scaled down to sum to it."""
    pre_counts = np.asarray(pre_counts)
    r = float(np.clip(p_success.sum(), 0.0, 1.0))
    if r > max_success_share:
        p_success, r = np.asarray(p_success) * (max_success_share / r), max_success_share
    n_success = int(round(r * size))
    from_success = apportion(n_success, p_success)
    pre_weights = pre_counts * np.clip(1.0 - p_success, 0.0, None)
    from_pre = apportion(size - n_success, pre_weights, minimum_one=pre_counts > 0)
    return from_success, from_pre


def build_sampled_set(
    pre: Transitions,
    successful: Transitions,
    p_success: np.ndarray,
    size: int,
    rng: np.random.Generator,
    pre_classes: np.ndarray | None = None,
    successful_classes: np.ndarray | None = None,
    max_success_share: float = 1.0,
) -> Transitions:
    """I^s by the sampling rule; a class with fewer transitions than its share is drawn with replacement.
    ``successful`` holds only transitions of rollouts that reached the goal. The classes of each transition are
    its (discrete) actions unless given (``*_classes``: action cells of continuous actions)."""
    n_classes = len(p_success)
    pre_classes = pre.actions if pre_classes is None else pre_classes
    successful_classes = successful.actions if successful_classes is None else successful_classes
    pre_counts = np.bincount(pre_classes, minlength=n_classes)[:n_classes]
    from_success, from_pre = sampling_counts(p_success, pre_counts, size, max_success_share)
    picks = []
    for source, classes, counts in ((successful, successful_classes, from_success), (pre, pre_classes, from_pre)):
        for cls, count in enumerate(counts):
            if count == 0:
                continue
            pool = np.flatnonzero(classes == cls)
            if len(pool) == 0:
                raise ValueError(f"no transitions of action class {cls} to draw {count} samples from")
            picks.append(source.take(rng.choice(pool, size=count, replace=count > len(pool))))
    return Transitions.concat(picks)


class ActionCells:
    """A partition of a continuous action space into ``k`` cells: k-means (k-means++ start, Lloyd iterations) on
    actions scaled to [-1, 1] per dimension; a cell is the set of actions nearest to one centre.
    By hand because a 20-line Lloyd loop is all it needs (scikit-learn/scipy are not otherwise dependencies)."""

    def __init__(self, centres: np.ndarray, low: np.ndarray, high: np.ndarray):
        self.centres, self.low, self.high = centres, np.asarray(low, np.float64), np.asarray(high, np.float64)

    @property
    def k(self) -> int:
        return len(self.centres)

    def _scaled(self, actions: np.ndarray) -> np.ndarray:
        actions = np.asarray(actions, np.float64).reshape(len(actions), -1)
        return 2.0 * (actions - self.low) / np.maximum(self.high - self.low, 1e-12) - 1.0

    @classmethod
    def fit(cls, actions: np.ndarray, k: int, low: np.ndarray, high: np.ndarray, seed: int, iterations: int = 50):
        """Cells fitted on ``actions`` (N, D); fewer than ``k`` when there are fewer distinct actions."""
        cells = cls(np.zeros((0, np.asarray(low).size)), low, high)
        points = np.unique(cells._scaled(actions), axis=0)
        rng = np.random.default_rng(seed)
        k = min(k, len(points))
        centres = [points[rng.integers(len(points))]]
        for _ in range(1, k):  # k-means++: the next centre far from the chosen ones
            distance = ((points[:, None, :] - np.asarray(centres)[None]) ** 2).sum(-1).min(1)
            centres.append(points[rng.choice(len(points), p=distance / distance.sum())])
        centres = np.asarray(centres)
        for _ in range(iterations):
            assign = ((points[:, None, :] - centres[None]) ** 2).sum(-1).argmin(1)
            moved = np.array([points[assign == c].mean(0) if (assign == c).any() else centres[c] for c in range(k)])
            if np.allclose(moved, centres):
                break
            centres = moved
        cells.centres = centres
        return cells

    def assign(self, actions: np.ndarray) -> np.ndarray:
        """The cell of each action (N,) int64."""
        if len(actions) == 0:
            return np.zeros(0, dtype=np.int64)
        scaled = self._scaled(actions)
        out = np.empty(len(scaled), dtype=np.int64)
        for start in range(0, len(scaled), 65536):
            part = scaled[start : start + 65536]
            out[start : start + 65536] = ((part[:, None, :] - self.centres[None]) ** 2).sum(-1).argmin(1)
        return out


def selects(env_success_rate: float, goal_rate: float, best: tuple[float, float]) -> bool:
    """Model selection (never by reward): a cycle's rollouts replace the selected model when their rate of the env's
    own success (what lerobot-eval counts) is higher, or equal with a goal rate at least as high; ``best`` holds
    the selected cycle's (env success, goal) rates, (-1, -1) before any. Ties go to the latest cycle."""
    return (env_success_rate, goal_rate) >= best


def held_out_split(
    n: int, rng: np.random.Generator, fraction: float = 0.1, classes: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of ``n`` items split into a training part and a held-out part (``fraction`` of them, at least one
    when ``n`` > 1). Split before I^s is drawn with replacement, so no copy of a held-out item is trained on.
    With ``classes``, a class whose items all fell in the held-out part keeps them for training instead: the
    sampling rule draws each class it gives a share from the training part."""
    order = rng.permutation(n)
    held = int(n * fraction) if n * fraction >= 1 else min(1, n - 1)
    train, held_out = order[held:], order[:held]
    if classes is not None:
        classes = np.asarray(classes)
        back = np.isin(classes[held_out], np.setdiff1d(classes[held_out], classes[train]))
        train, held_out = np.concatenate([train, held_out[back]]), held_out[~back]
    return np.sort(train), np.sort(held_out)


def r_squared(predicted: np.ndarray, true: np.ndarray) -> float:
    """Coefficient of determination averaged over action dimensions (1 = exact; 0 = no better than the mean)."""
    predicted = np.asarray(predicted, np.float64).reshape(len(true), -1)
    true = np.asarray(true, np.float64).reshape(len(true), -1)
    variance = true.var(axis=0)
    keep = variance > 1e-12
    if not keep.any():
        return float("nan")
    return float(np.mean(1.0 - ((predicted - true) ** 2).mean(axis=0)[keep] / variance[keep]))


def performance(returns: np.ndarray, expert_return: float, random_return: float) -> float:
    """P: mean over episodes of (R − R_random) / (R_expert − R_random); 0 = random, 1 = expert."""
    return float(np.mean((np.asarray(returns) - random_return) / (expert_return - random_return)))
