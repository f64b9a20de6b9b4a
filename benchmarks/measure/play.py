"""Which pre-demonstrations let an IDM label SO-101's expert: an IDM trained (`lerobot-train --policy.type=iupe
--policy.supervised=true --policy.idm_context=0`, the IUPE cycle's pair IDM) on uniformly random or on play
pre-demonstrations (`lerobot-iupe-collect --agent=random|play`, seeds 1000…) relabels held-out scripted-expert
episodes (seeds 700000…, collected with actions, stripped with LeRobot's `remove_feature`); the labels are scored
per action dimension (R²) against the true actions. Each IDM reads either the whole observation (the arm's state,
the block and the goal) or the arm's state only (`--policy.idm_observation_keys=[observation.state]`).

    python benchmarks/measure/play.py [--episodes 30] [--expert_episodes 20]

Writes benchmarks/pre_demos.json and benchmarks/pre_demos.md.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_tools import remove_feature

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, write_page  # noqa: E402

from lerobot_iupe.benchmark.runner import CHECKPOINT, run_cli
from lerobot_iupe.data.readers import action_array, column_array

ENV = "so101_pickplace"
NAMES = ("dx", "dy", "dz", "grasp")
IDM_KEYS = {"whole observation": None, "arm state only": "observation.state"}


def collect(root: Path, agent: str, episodes: int, seed: int) -> Path:
    if not (root / "meta" / "info.json").exists():
        run_cli(
            "lerobot-iupe-collect", f"--env.type={ENV}", f"--agent={agent}", f"--episodes={episodes}",
            f"--seed={seed}", "--keep_actions=true", f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}",
            "--overwrite=true", quiet=True,
        )  # fmt: skip
    return root


def inner_actions(root: Path) -> np.ndarray:
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    episodes = column_array(dataset.hf_dataset, "episode_index")
    return action_array(dataset)[np.append(episodes[:-1] == episodes[1:], False)]


def per_dimension_r2(labels: np.ndarray, true: np.ndarray) -> list[float]:
    return [float(1 - ((labels - true) ** 2).mean(0)[i] / true.var(0)[i]) for i in range(true.shape[1])]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=30, help="pre-demonstration episodes per agent")
    parser.add_argument("--expert_episodes", type=int, default=20, help="held-out expert episodes to relabel")
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--work", default="outputs/measure-play")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    truth = collect(work / "expert-held-out", "expert", args.expert_episodes, 700_000)
    true = inner_actions(truth)
    rows = []
    for agent in ("random", "play"):
        pre = collect(work / f"{agent}-{args.episodes}", agent, args.episodes, 1000)
        frames = LeRobotDataset(f"local/{pre.name}", root=pre).num_frames
        for reads, key in IDM_KEYS.items():
            tag = f"{agent}-{args.episodes}-{'all' if key is None else 'state'}"
            idm = work / f"idm-{tag}"
            if not (idm / CHECKPOINT).exists():
                shutil.rmtree(idm, ignore_errors=True)
                keys = [] if key is None else [f"--policy.idm_observation_keys=[{key}]"]
                run_cli(
                    "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", "--policy.idm_context=0",
                    *keys, f"--dataset.repo_id=local/{pre.name}", f"--dataset.root={pre}", f"--output_dir={idm}",
                    f"--steps={args.steps}", f"--save_freq={args.steps}", "--batch_size=64", "--num_workers=0",
                    "--policy.device=cpu", "--wandb.enable=false", "--seed=0", "--log_freq=500", quiet=True,
                )  # fmt: skip
            stripped = work / f"relabelled-{tag}"
            shutil.rmtree(stripped, ignore_errors=True)
            source = LeRobotDataset(f"local/{truth.name}", root=truth, video_backend="pyav")
            remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
            run_cli(
                "lerobot-iupe-relabel", f"--policy.path={idm / CHECKPOINT}",
                f"--dataset.repo_id=local/{stripped.name}", f"--dataset.root={stripped}", quiet=True,
            )  # fmt: skip
            r2 = per_dimension_r2(inner_actions(stripped), true)
            rows.append({"agent": agent, "idm_reads": reads, "frames": frames, "r2": r2})
            print(rows[-1], flush=True)
    command = command_line()
    table = [
        "| pre-demonstrations | IDM reads | frames | " + " | ".join(f"R² {n}" for n in NAMES) + " | mean |",
        "|---|---|---|" + "---|" * (len(NAMES) + 1),
    ]
    for row in rows:
        cells = " | ".join(f"{x:.3f}" for x in row["r2"])
        table.append(f"| {row['agent']} | {row['idm_reads']} | {row['frames']} | {cells} | {np.mean(row['r2']):.3f} |")
    intro = (
        f"a pair IDM (k = 0) trained on {args.episodes} pre-demonstration episodes ({args.steps} steps, batch 64) "
        f"relabels {args.expert_episodes} held-out scripted-expert episodes; R² against the true actions."
    )
    title = "Pre-demonstrations for SO-101: uniformly random against goal-agnostic play"
    write_page(out, "pre_demos", command, rows, title, intro, table)


if __name__ == "__main__":
    main()
