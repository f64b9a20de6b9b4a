"""The algorithmic core of IUPE as small pure functions: label/action choice, Eq. 1, the sampling rule, metrics."""

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


def sampling_counts(p_success: np.ndarray, pre_counts: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """How many transitions per action to take from successful runs and from pre-demonstrations.

    With r = Σ P(a|E): share r of ``size`` from successful runs, per action ∝ P(a|E); share 1 − r from
    pre-demonstrations, per action ∝ n_pre(a) · (1 − P(a|E)) ("inverse probability" applied to I_pre's own action
    frequencies, so that r = 0 gives I_pre's distribution — I_pre itself at size |I_pre| — also when I_pre is not
    balanced; on a balanced I_pre this is the paper's ∝ 1 − P(a|E)). Every action present in I_pre is kept (at
    least one sample) while r < 1."""
    pre_counts = np.asarray(pre_counts)
    r = float(np.clip(p_success.sum(), 0.0, 1.0))
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
) -> Transitions:
    """I^s by the sampling rule; a class with fewer transitions than its share is drawn with replacement.
    ``successful`` holds only transitions of rollouts that reached the goal."""
    n_actions = len(p_success)
    pre_counts = np.bincount(pre.actions, minlength=n_actions)[:n_actions]
    from_success, from_pre = sampling_counts(p_success, pre_counts, size)
    picks = []
    for source, counts in ((successful, from_success), (pre, from_pre)):
        for action, count in enumerate(counts):
            if count == 0:
                continue
            pool = np.flatnonzero(source.actions == action)
            if len(pool) == 0:
                raise ValueError(f"no transitions of action {action} to draw {count} samples from")
            picks.append(source.take(rng.choice(pool, size=count, replace=count > len(pool))))
    return Transitions.concat(picks)


def performance(returns: np.ndarray, expert_return: float, random_return: float) -> float:
    """P: mean over episodes of (R − R_random) / (R_expert − R_random); 0 = random, 1 = expert."""
    return float(np.mean((np.asarray(returns) - random_return) / (expert_return - random_return)))
