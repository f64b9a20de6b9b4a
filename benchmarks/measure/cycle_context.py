"""The IUPE cycle's first IDM against its window k and the keys it reads, on Meta-World: trained as the cycle trains
it (``fit_idm`` on the play pre-demonstrations I_pre, a tenth held out as the cycle holds it out, 10 epochs of batch
256), then scored by R² on the expert's
own actions (the benchmark's expert dataset collected with them), every transition of the 10 episodes, by action
dimension too (hand x, y, z, grasp); beside it a ridge regression per dimension on the same windows and data, the
simplest fit to beat. Means over seeds; a dimension the expert holds constant (the grasp of most tasks) has no R²
(–), and the means are over the others.

    python benchmarks/measure/cycle_context.py --work outputs/metaworld [--tasks push pick-place] [--ks 0 1 2 3 4]
    python benchmarks/measure/cycle_context.py --work outputs/metaworld outputs/mw-hold --ks 3 --keys state \
        --page cycle_play

Reads the datasets the Meta-World benchmark collected under ``<work>/data`` (several work folders: the same
expert beside each folder's pre-demonstrations, e.g. play collected with other ``--env.play_held_moves``); writes
benchmarks/<page>.md and .json (page: cycle_context).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.policies.factory import make_policy
from lerobot.utils.constants import OBS_STATE

from lerobot_iupe.data.readers import load_transitions
from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.algorithm import held_out_split, r_squared
from lerobot_iupe.policy.idm_fit import fit_idm

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, write_page  # noqa: E402

KEYS = {"all": None, "state": [OBS_STATE]}


def dataset(work: Path, task: str, kind: str) -> LeRobotDataset:
    (root,) = sorted((work / "data").glob(f"mw-{task}-*-{kind}"))
    return LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")


def ridge_r2(train_x: np.ndarray, train_y: np.ndarray, test_x: np.ndarray, test_y: np.ndarray) -> float:
    """Ridge (λ = 1e-3 · n on standardised inputs) from flattened windows [s_t, s_j − s_t] to the action. A fixed
    strength, not ``joint_idm.fit_ridge``'s choice on held-out blocks of the training data: chosen on play, that
    choice labelled the expert worse (push, hand state, k = 3: x / y / z R² 0.58 / 0.67 / 0.01 against 0.90 / 0.79 /
    0.32)."""

    def features(windows: np.ndarray, k: int) -> np.ndarray:
        s = windows[:, k : k + 1]
        return np.concatenate([s, np.delete(windows, k, axis=1) - s], axis=1).reshape(len(windows), -1)

    k = (train_x.shape[1] - 2) // 2
    a, b = features(train_x, k), features(test_x, k)
    mean, std = a.mean(0), a.std(0) + 1e-6
    a, b = np.c_[(a - mean) / std, np.ones(len(a))], np.c_[(b - mean) / std, np.ones(len(b))]
    weights = np.linalg.solve(a.T @ a + 1e-3 * len(a) * np.eye(a.shape[1]), a.T @ train_y)
    return r_squared(b @ weights, test_y)


def held_moves(pre: LeRobotDataset) -> float:
    """The share of held moves the play pre-demonstrations were collected with (0 before the setting existed)."""
    return float(read_iupe_meta(Path(pre.root))["env"].get("play_held_moves", 0.0))


def measure(work: Path, task: str, k: int, keys: str, seed: int, linear_part: bool = False) -> dict:
    pre, expert = dataset(work, task, "random"), dataset(work, task, "expert-actions")
    config = IUPEConfig(
        pre_demos_repo_id=pre.repo_id, pre_demos_root=str(pre.root), idm_context=k, idm_observation_keys=KEYS[keys],
        idm_linear_part=linear_part, device="cpu",
    )  # fmt: skip
    torch.manual_seed(seed)
    policy = make_policy(config, ds_meta=expert.meta)
    read = config.idm_keys
    train = load_transitions(pre, config.observation_keys, context=k)
    test = load_transitions(expert, config.observation_keys, context=k)
    # As the cycle starts: a tenth of I_pre held out to score it, and no rollout yet to judge a linear part's gate on.
    train_part, held_part = held_out_split(len(train), np.random.default_rng([seed, 0, 1]))
    train, held = train.take(train_part), train.take(held_part)
    optimizer = torch.optim.Adam(policy.idm_parameters(), lr=config.idm_lr)
    fit_idm(policy, optimizer, train, held, np.random.default_rng(seed))
    policy.eval()
    with torch.no_grad():
        labels = policy.idm_head.mode(policy.idm_window_output(torch.as_tensor(test.windows))).numpy()
    r2 = r_squared(labels, test.actions)
    columns = policy.layout.indices(config.observation_keys.index(key) for key in read)
    ridge = [
        ridge_r2(train.windows[..., columns], train.actions[:, [d]], test.windows[..., columns], test.actions[:, [d]])
        for d in range(test.actions.shape[1])
    ]
    by_dimension = [r_squared(labels[:, d], test.actions[:, d]) for d in range(test.actions.shape[1])]
    return {
        "task": task, "k": k, "keys": keys, "seed": seed, "play_held_moves": held_moves(pre),
        "idm_r2": r2, "idm_r2_by_dimension": by_dimension,
        "ridge_r2": float(np.nanmean(ridge)), "ridge_r2_by_dimension": ridge,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, nargs="+", default=[Path("outputs/metaworld")])
    parser.add_argument("--out", default="benchmarks")
    parser.add_argument("--page", default="cycle_context", help="the page's name in --out")
    parser.add_argument("--tasks", nargs="+", default=["push", "pick-place", "peg-insert-side"])
    parser.add_argument("--ks", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    parser.add_argument("--keys", nargs="+", default=list(KEYS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0])
    parser.add_argument("--linear_part", action="store_true", help="--policy.idm_linear_part=true (linear_prior.py)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for task in args.tasks:
        for work in args.work:
            for keys in args.keys:
                for k in args.ks:
                    for seed in args.seeds:
                        rows.append(measure(work, task, k, keys, seed, args.linear_part))
                        print(json.dumps(rows[-1]), flush=True)
    table = [
        "| task | play's held moves | IDM reads | k | IDM R² | its x / y / z / grasp | ridge R² "
        "| its x / y / z / grasp |",
        "|---|---|---|---|---|---|---|---|",
    ]
    settings = {(r["task"], r["play_held_moves"], r["keys"], r["k"]) for r in rows}
    for task, held, keys, k in sorted(settings, key=lambda s: (args.tasks.index(s[0]), s[1:])):
        same = [r for r in rows if (r["task"], r["play_held_moves"], r["keys"], r["k"]) == (task, held, keys, k)]
        cells = []
        for fit in ("idm", "ridge"):
            dims = np.mean([r[f"{fit}_r2_by_dimension"] for r in same], axis=0)
            by_dimension = " / ".join("–" if np.isnan(v) else f"{v:.2f}" for v in dims)
            cells += [f"{np.mean([r[f'{fit}_r2'] for r in same]):.2f}", by_dimension]
        table.append(f"| {task} | {held:g} | {keys} | {k} | {' | '.join(cells)} |")
    title = "The IUPE cycle's first IDM on Meta-World: its window k, the keys it reads, the play it learns from"
    write_page(Path(args.out), args.page, command_line(), rows, title, __doc__.split("\n\n")[0], table)


if __name__ == "__main__":
    main()
