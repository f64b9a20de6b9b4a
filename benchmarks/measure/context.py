"""IDM accuracy against its context k (frames t-k … t+1+k): per env, an IDM is trained with
`lerobot-train --policy.type=iupe --policy.supervised=true --policy.idm_context=k` on 10 labelled expert episodes
(seeds 1000…), then relabels 50 held-out expert episodes (seeds 700000…) collected with actions and stripped of
them (LeRobot's `remove_feature`); the labels are scored against the true actions on every frame with a successor:
agreement for discrete actions, R² (and, for LunarLander, R² of the engine effects) for continuous ones.

    python benchmarks/measure/context.py [--envs cartpole acrobot ...] [--ks 0 1 2]

Writes the "context" section of benchmarks/relabel.json and renders benchmarks/relabel.md.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_tools import remove_feature

from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.policy.algorithm import r_squared

sys.path.insert(0, str(Path(__file__).parent))
from downstream import lunar_effect  # noqa: E402
from relabel_report import render, update  # noqa: E402
from steps import CHECKPOINT, command_line, parse_with_folders, run, train_once  # noqa: E402

ENVS = {"cartpole": 1500, "mountaincar": 1500, "acrobot": 1500, "lunarlander": 2000, "so101_pickplace": 2000}


def collect(env: str, root: Path, episodes: int, seed: int) -> None:
    if not root.exists():
        run(
            "lerobot-iupe-collect", f"--env.type={env}", "--agent=expert", f"--episodes={episodes}", f"--seed={seed}",
            "--keep_actions=true", f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}",
        )  # fmt: skip


def inner_actions(root: Path) -> np.ndarray:
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    episodes = column_array(dataset.hf_dataset, "episode_index")
    return action_array(dataset)[np.append(episodes[:-1] == episodes[1:], False)]


def measure(env: str, k: int, work: Path) -> dict:
    labelled, truth = work / f"{env}-labelled", work / f"{env}-held-out"
    collect(env, labelled, 10, 1000)
    collect(env, truth, 50, 700000)
    out = work / f"{env}-k{k}"
    flags = ["--policy.type=iupe", "--policy.supervised=true", f"--policy.idm_context={k}", "--batch_size=64"]
    train_once(labelled, out, *flags, "--seed=0", "--log_freq=500", steps=ENVS[env], threads=None)
    stripped = work / f"{env}-k{k}-relabelled"
    shutil.rmtree(stripped, ignore_errors=True)
    source = LeRobotDataset(f"local/{truth.name}", root=truth, video_backend="pyav")
    remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
    run("lerobot-iupe-relabel", f"--policy.path={out / CHECKPOINT}", f"--dataset.repo_id=local/{stripped.name}",
        f"--dataset.root={stripped}")  # fmt: skip
    true, labels = inner_actions(truth), inner_actions(stripped)
    continuous = true.dtype.kind == "f"
    row = {
        "env": env,
        "k": k,
        "trained_on": "10 labelled expert episodes",
        "frames": int(len(true)),
        "score": r_squared(labels, true) if continuous else float((labels == true).mean()),
        "metric": "r2" if continuous else "agreement",
    }
    if env == "lunarlander":
        row["effect_r2"] = r_squared(lunar_effect(labels), lunar_effect(true))
    print(row, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=list(ENVS))
    parser.add_argument("--ks", nargs="+", type=int, default=[0, 1, 2])
    args = parse_with_folders(parser, "outputs/measure-context")
    work, command = Path(args.work), command_line()
    for env in args.envs:
        rows = [measure(env, k, work) for k in args.ks]
        update(Path(args.out), "context", rows, command, key=("env", "k"))
    print(render(Path(args.out)))


if __name__ == "__main__":
    main()
