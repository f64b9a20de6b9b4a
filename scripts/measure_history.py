"""Policies that remember, measured: BC on SO-101 pick-and-place's true actions with the policy model reading its
last n observations (`--policy.n_obs_steps=n`), against n = 1. Data: 50 scripted-expert episodes with actions
(`lerobot-iupe-collect --agent=expert --keep_actions=true`, seeds 0…), the benchmark's budget (3,000 steps, batch
64); evaluation as `lerobot-eval` runs it by default (the Gaussian's mode) on 50 episodes, seeds 500000…, at the
env's 300-step cap.

    python scripts/measure_history.py [--ns 1 4] [--seeds 0 1 2] [--jobs 2]

Writes benchmarks/history.json and benchmarks/history.md.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from relabel_report import write_page

from lerobot_iupe.benchmark.evaluation import evaluate_checkpoint
from lerobot_iupe.benchmark.runner import CHECKPOINT, run_cli
from lerobot_iupe.envs.configs import env_config_from_settings

ENV = {"type": "so101_pickplace"}
STEPS, BATCH, EPISODES, EVAL_EPISODES = 3000, 64, 50, 50


def train(data: Path, out: Path, n: int, seed: int) -> Path:
    if not (out / CHECKPOINT).exists():
        shutil.rmtree(out, ignore_errors=True)
        run_cli(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", f"--policy.n_obs_steps={n}",
            f"--dataset.repo_id=local/{data.name}", f"--dataset.root={data}", f"--output_dir={out}",
            f"--steps={STEPS}", f"--save_freq={STEPS}", f"--batch_size={BATCH}", "--num_workers=0",
            "--policy.device=cpu", "--wandb.enable=false", f"--seed={seed}", "--log_freq=500",
            log=out.with_suffix(".log"), quiet=True, threads=1,
        )  # fmt: skip
    return out / CHECKPOINT


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ns", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--jobs", type=int, default=2, help="trainings at once, one thread each")
    parser.add_argument("--work", default="outputs/measure-history")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    data = work / "so101-expert-actions"
    if not (data / "meta" / "info.json").exists():
        run_cli(
            "lerobot-iupe-collect", *[f"--env.{k}={v}" for k, v in ENV.items()], "--agent=expert",
            f"--episodes={EPISODES}", "--seed=0", "--keep_actions=true", f"--dataset.repo_id=local/{data.name}",
            f"--dataset.root={data}", "--overwrite=true",
        )  # fmt: skip
    runs = [(n, seed) for n in args.ns for seed in args.seeds]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        checkpoints = list(pool.map(lambda r: train(data, work / f"bc-n{r[0]}-s{r[1]}", *r), runs))
    env_cfg = env_config_from_settings(ENV)
    rows = []
    for (n, seed), checkpoint in zip(runs, checkpoints, strict=True):
        overall = evaluate_checkpoint(checkpoint, env_cfg, EVAL_EPISODES, "argmax")
        rows.append({"n_obs_steps": n, "seed": seed, "success": overall["pc_success"] / 100})
        print(rows[-1], flush=True)
    command = " ".join(["python", "scripts/measure_history.py", *sys.argv[1:]])
    table = ["| n_obs_steps | success per seed | mean ± std (ddof 1) |", "|---|---|---|"]
    for n in args.ns:
        success = np.array([r["success"] for r in rows if r["n_obs_steps"] == n])
        spread = f" ± {success.std(ddof=1):.2f}" if len(success) > 1 else ""
        table.append(f"| {n} | {' / '.join(f'{s:.2f}' for s in success)} | {success.mean():.2f}{spread} |")
    intro = (
        f"BC on {EPISODES} scripted-expert episodes' true actions ({STEPS} steps, batch {BATCH}), success over "
        f"{EVAL_EPISODES} episodes (seeds 500000…, cap {env_cfg.episode_length}) by the Gaussian's mode, as "
        "`lerobot-eval` plays it by default."
    )
    title = "Policies that remember: BC on SO-101 pick-and-place with an observation history"
    write_page(out, "history", command, rows, title, intro, table)


if __name__ == "__main__":
    main()
