"""Policies that remember, measured: BC on SO-101 pick-and-place's true actions with the policy model reading its
last n observations (`--policy.n_obs_steps=n`), against n = 1. Data: 50 scripted-expert episodes with actions
(`lerobot-iupe-collect --agent=expert --keep_actions=true`, seeds 0…), the benchmark's budget (3,000 steps, batch
64); evaluation as `lerobot-eval` runs it by default (the Gaussian's mode) on 50 episodes, seeds 500000…, at the
env's 300-step cap. `--ema_decay=d` trains with the policy model's weight average (`--policy.ema_decay=d`),
`--steps` longer or shorter, `--hidden_dim` wider; the rows of other settings already in history.json are kept.

    python scripts/measure_history.py [--ns 1 4] [--seeds 0 1 2] [--jobs 2] [--ema_decay 0.995] [--steps 3000]
        [--hidden_dim 64]

Writes benchmarks/history.json and benchmarks/history.md.
"""

from __future__ import annotations

import argparse
import json
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
HIDDEN = 64  # the policy's default hidden_dim


def run_name(n: int, seed: int, ema_decay: float, steps: int, hidden: int) -> str:
    """The default setting keeps the first runs' names."""
    average = f"-ema{str(ema_decay).replace('.', 'p')}" if ema_decay else ""
    width = "" if hidden == HIDDEN else f"-h{hidden}"
    return f"bc-n{n}-s{seed}{average}{'' if steps == STEPS else f'-{steps}steps'}{width}"


def train(data: Path, out: Path, n: int, seed: int, ema_decay: float, steps: int, hidden: int) -> Path:
    if not (out / CHECKPOINT).exists():
        shutil.rmtree(out, ignore_errors=True)
        run_cli(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", f"--policy.n_obs_steps={n}",
            f"--dataset.repo_id=local/{data.name}", f"--dataset.root={data}", f"--output_dir={out}",
            f"--steps={steps}", f"--save_freq={steps}", f"--batch_size={BATCH}", "--num_workers=0",
            "--policy.device=cpu", "--wandb.enable=false", f"--seed={seed}", "--log_freq=500",
            f"--policy.ema_decay={ema_decay}", f"--policy.hidden_dim={hidden}",
            log=out.parent / f"{out.name}.log", quiet=True, threads=1,
        )  # fmt: skip
    return out / CHECKPOINT


def setting(row: dict) -> tuple[int, float, int, int]:
    """Rows measured before the weight average, --steps and --hidden_dim existed are the defaults'."""
    return row["n_obs_steps"], row.get("ema_decay", 0.0), row.get("steps", STEPS), row.get("hidden_dim", HIDDEN)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ns", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--jobs", type=int, default=2, help="trainings at once, one thread each")
    parser.add_argument("--ema_decay", type=float, default=0.0, help="--policy.ema_decay of every run (0: none)")
    parser.add_argument("--steps", type=int, default=STEPS, help="lerobot-train --steps of every run")
    parser.add_argument("--hidden_dim", type=int, default=HIDDEN, help="--policy.hidden_dim of every run")
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
    setup = (args.ema_decay, args.steps, args.hidden_dim)
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        checkpoints = list(pool.map(lambda r: train(data, work / run_name(*r, *setup), *r, *setup), runs))
    env_cfg = env_config_from_settings(ENV)
    rows = []
    for (n, seed), checkpoint in zip(runs, checkpoints, strict=True):
        overall = evaluate_checkpoint(checkpoint, env_cfg, EVAL_EPISODES, "argmax")
        success = overall["pc_success"] / 100
        rows.append({
            "n_obs_steps": n, "ema_decay": args.ema_decay, "steps": args.steps, "hidden_dim": args.hidden_dim,
            "seed": seed, "success": success,
        })  # fmt: skip
        print(rows[-1], flush=True)
    command = " ".join(["python", "scripts/measure_history.py", *sys.argv[1:]])
    commands = {}
    if (out / "history.json").exists():  # rows of other settings stay, with their own command
        before = json.loads((out / "history.json").read_text())
        new = {setting(r) for r in rows}
        kept = [r for r in before["rows"] if setting(r) not in new]
        # a page from before per-setting commands has one command for all its rows
        recorded = before.get("commands") or {str(setting(r)): before["command"] for r in kept}
        commands = {str(setting(r)): recorded[str(setting(r))] for r in kept}
        rows = kept + rows
    commands.update({str(setting(r)): command for r in rows if str(setting(r)) not in commands})
    table = [
        "| n_obs_steps | weight average (ema_decay) | steps | hidden_dim | success per seed | mean ± std (ddof 1) "
        "| command |",
        "|---|---|---|---|---|---|---|",
    ]
    for key in sorted({setting(r) for r in rows}):
        success = np.array([r["success"] for r in rows if setting(r) == key])
        spread = f" ± {success.std(ddof=1):.2f}" if len(success) > 1 else ""
        table.append(
            f"| {key[0]} | {key[1] or 'none'} | {key[2]} | {key[3]} | {' / '.join(f'{s:.2f}' for s in success)} | "
            f"{success.mean():.2f}{spread} | `{commands[str(key)]}` |"
        )
    intro = (
        f"BC on {EPISODES} scripted-expert episodes' true actions (batch {BATCH}), success over {EVAL_EPISODES} "
        f"episodes (seeds 500000…, cap {env_cfg.episode_length}) by the Gaussian's mode, as `lerobot-eval` plays it "
        "by default; every setting on the same data and evaluation episodes."
    )
    title = "Policies that remember: BC on SO-101 pick-and-place with an observation history"
    write_page(out, "history", command, rows, title, intro, table)
    page = json.loads((out / "history.json").read_text())
    (out / "history.json").write_text(json.dumps({**page, "commands": commands}, indent=1) + "\n")


if __name__ == "__main__":
    main()
