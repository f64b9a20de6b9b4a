"""How much of the network's correction the cycle's first IDM should keep on Meta-World, when its linear part
(``--policy.idm_linear_part``) and its network are fitted on play alone: the IDM trained as the cycle trains it
(``fit_idm`` on the play pre-demonstrations I_pre, a tenth held out, window k = 3 of the hand's state), then scored by
R² on the expert's own actions (hand x / y / z, the mean over the dimensions the expert moves) with the network's
share per dimension chosen five ways: none (the linear part alone, the rule since this measurement), all of it, the
share that fits held-out play best (the earlier rule), the share that fits the held-out play transition nearest each
expert window best (standardised linear-part features; the expert's states are known to the cycle, its actions are
not), and none with the linear part re-weighted toward the expert's states (a logistic regression telling expert
windows from play's, its odds as weights: the textbook correction of a covariate shift). Means over seeds.

    python benchmarks/measure/cycle_gate.py --work /tmp/w/mw --tasks reach push drawer-open button-press-topdown \
        --seeds 0 1 --page cycle_gate

Reads the datasets the Meta-World benchmark collected under ``<work>/data``; writes benchmarks/<page>.md and .json.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from lerobot.policies.factory import make_policy

from lerobot_iupe.data.readers import load_transitions
from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.algorithm import held_out_split, r_squared
from lerobot_iupe.policy.idm_fit import fit_idm
from lerobot_iupe.policy.joint_idm import gate_weights
from lerobot_iupe.policy.linear_prior import SHIFT_STRENGTH

sys.path.insert(0, str(Path(__file__).parent))
from cycle_context import KEYS, dataset  # noqa: E402
from steps import command_line, write_page  # noqa: E402

RULES = ["none", "all", "held-out play", "nearest play", "re-weighted linear part"]


def expert_odds(play: np.ndarray, expert: np.ndarray, strength: float = 1e-2) -> np.ndarray:
    """Per play row, the odds that a logistic regression (L2 ``strength``, classes weighted equally) gives it of
    being an expert window, normalised to mean 1 and capped at 20."""
    x = torch.as_tensor(np.r_[play, expert], dtype=torch.float64)
    y = torch.as_tensor(np.r_[np.zeros(len(play)), np.ones(len(expert))])
    weight = torch.as_tensor(np.r_[np.full(len(play), 0.5 / len(play)), np.full(len(expert), 0.5 / len(expert))])
    w = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
    b = torch.zeros((), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.LBFGS([w, b], max_iter=200, line_search_fn="strong_wolfe")

    def closure():
        optimizer.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(x @ w + b, y, weight=weight, reduction="sum")
        (loss + strength * (w**2).sum()).backward()
        return loss

    optimizer.step(closure)
    with torch.no_grad():
        odds = torch.exp(torch.clamp(x[: len(play)] @ w + b, -20, 20)).numpy()
    odds = np.minimum(odds / odds.mean(), 20)
    return odds / odds.mean()


def weighted_ridge(x: np.ndarray, y: np.ndarray, weights: np.ndarray, test: np.ndarray) -> np.ndarray:
    """The linear part's fit (standardised features, strength ``SHIFT_STRENGTH`` · n) with row ``weights``."""
    mean, std = x.mean(0), x.std(0) + 1e-6
    a = np.c_[(x - mean) / std, np.ones(len(x))]
    penalty = np.diag(np.r_[np.ones(x.shape[1]), 0.0])
    coef = np.linalg.solve(
        a.T @ (a * weights[:, None]) + SHIFT_STRENGTH * weights.sum() * penalty, (a * weights[:, None]).T @ y
    )
    return np.c_[(test - mean) / std, np.ones(len(test))] @ coef


def measure(work: Path, task: str, seed: int) -> dict:
    pre, expert = dataset(work, task, "random"), dataset(work, task, "expert-actions")
    config = IUPEConfig(
        pre_demos_repo_id=pre.repo_id, pre_demos_root=str(pre.root), idm_context=3, idm_observation_keys=KEYS["state"],
        idm_linear_part=True, device="cpu",
    )  # fmt: skip
    torch.manual_seed(seed)
    policy = make_policy(config, ds_meta=expert.meta)
    play = load_transitions(pre, config.observation_keys, context=3)
    test = load_transitions(expert, config.observation_keys, context=3)
    train_part, held_part = held_out_split(len(play), np.random.default_rng([seed, 0, 1]))
    train, held = play.take(train_part), play.take(held_part)
    fit_idm(
        policy, torch.optim.Adam(policy.idm_parameters(), lr=config.idm_lr), train, held, np.random.default_rng(seed)
    )
    policy.eval()
    prior, head = policy.idm_prior, policy.idm_head
    prior.gate.fill_(1.0)

    def parts(data):
        """The linear part's labels, the network's whole correction and the actions (the head's scaled units)."""
        window = torch.as_tensor(data.windows)
        with torch.no_grad():
            shift = head._scale(prior(window))
            whole = policy.idm_window_output(window)[:, : config.action_dim]
        return shift.numpy(), (whole - shift).numpy(), head._scale(torch.as_tensor(data.actions)).numpy()

    held_shift, held_correction, held_actions = parts(held)
    shift, correction, actions = parts(test)
    features = {
        name: prior.features(data.windows).astype(np.float64) for name, data in (("held", held), ("test", test))
    }
    mean, std = features["held"].mean(0), features["held"].std(0) + 1e-6
    a, b = (features["held"] - mean) / std, (features["test"] - mean) / std
    nearest = ((b**2).sum(1)[:, None] + (a**2).sum(1)[None] - 2 * b @ a.T).argmin(1)
    moved = np.flatnonzero(actions.std(0) > 1e-6)
    dims = [d for d in moved if not bool(head.binary[d])]

    def score(labels: np.ndarray) -> list[float]:
        return [
            float(r_squared(labels[:, d], actions[:, d])) if d in dims else float("nan") for d in range(len(labels[0]))
        ]

    shares = {
        "none": np.zeros(config.action_dim),
        "all": np.ones(config.action_dim),
        "held-out play": gate_weights(held_actions - held_shift, held_correction),
        "nearest play": gate_weights((held_actions - held_shift)[nearest], held_correction[nearest]),
    }
    by_rule = {rule: score(shift + share * correction) for rule, share in shares.items()}
    train_features = prior.features(train.windows).astype(np.float64)
    odds = expert_odds((train_features - mean) / std, b)
    reweighted = weighted_ridge(
        train_features, head._scale(torch.as_tensor(train.actions)).numpy(), odds, features["test"]
    )
    by_rule["re-weighted linear part"] = score(reweighted)
    return {
        "task": task, "seed": seed, "by_rule": by_rule,
        "shares": {rule: share.tolist() for rule, share in shares.items()},
        "odds_effective_rows": float(odds.sum() ** 2 / (odds**2).sum()), "play_rows": len(train),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("outputs/metaworld"))
    parser.add_argument("--out", default="benchmarks")
    parser.add_argument("--page", default="cycle_gate")
    parser.add_argument("--tasks", nargs="+", default=["reach", "push", "drawer-open", "button-press-topdown"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for task in args.tasks:
        for seed in args.seeds:
            rows.append(measure(args.work, task, seed))
            print(json.dumps(rows[-1]), flush=True)
    table = ["| task | " + " | ".join(RULES) + " |", "|---|" + "---|" * len(RULES)]
    for task in args.tasks:
        same = [r for r in rows if r["task"] == task]
        cells = []
        for rule in RULES:
            dims = np.mean([r["by_rule"][rule] for r in same], axis=0)
            shown = " / ".join(f"{v:.2f}" for v in dims[:3] if not np.isnan(v))
            cells.append(f"**{np.nanmean(dims):.2f}** ({shown})")
        table.append(f"| {task} | {' | '.join(cells)} |")
    title = "The cycle's first IDM on Meta-World: how much of the network, fitted on play, to keep"
    write_page(Path(args.out), args.page, command_line(), rows, title, __doc__.split("\n\n")[0], table)


if __name__ == "__main__":
    main()
