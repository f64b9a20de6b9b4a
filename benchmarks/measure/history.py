"""Policies that remember, measured: BC on SO-101 pick-and-place's true actions with the policy model reading its
last n observations (`--policy.n_obs_steps=n`), against n = 1. Data: 50 scripted-expert episodes with actions
(`lerobot-iupe-collect --agent=expert --keep_actions=true`, seeds 0…), the benchmark's budget (3,000 steps, batch
64); evaluation as `lerobot-eval` runs it by default (the Gaussian's mode) on 50 episodes, seeds 500000…, at the
env's 300-step cap. `--ema_decay=d` trains with the policy model's weight average (`--policy.ema_decay=d`),
`--steps` longer or shorter, `--hidden_dim` wider, `--binary_action_dims 3` plays the grasp as open or shut
(`--policy.binary_action_dims=[3]`), `--relative_positions` collects and evaluates with the block and goal also
seen from the end effector (`--env.relative_positions=true`, its own expert dataset of the same seeds); the rows
of other settings already in history.json are kept.

    python benchmarks/measure/history.py [--ns 1 4] [--seeds 0 1 2] [--jobs 2] [--ema_decay 0.995] [--steps 3000]
        [--hidden_dim 64] [--binary_action_dims 3] [--relative_positions]

Writes benchmarks/history.json and benchmarks/history.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, train_once, write_page  # noqa: E402

from lerobot_iupe.benchmark.evaluation import evaluate_checkpoint
from lerobot_iupe.benchmark.runner import run_cli
from lerobot_iupe.envs.configs import env_cli_flags, env_config_from_settings

ENV = {"type": "so101_pickplace"}
STEPS, BATCH, EPISODES, EVAL_EPISODES = 3000, 64, 50, 50
HIDDEN = 64  # the policy's default hidden_dim


class Setting(NamedTuple):
    """One row group of the table: everything but the seed."""

    n_obs_steps: int
    ema_decay: float
    steps: int
    hidden_dim: int
    binary_action_dims: tuple[int, ...]
    relative_positions: bool


def run_name(seed: int, setting: Setting) -> str:
    """The default setting keeps the first runs' names."""
    n, ema_decay, steps, hidden, binary, relative = setting
    average = f"-ema{str(ema_decay).replace('.', 'p')}" if ema_decay else ""
    width = "" if hidden == HIDDEN else f"-h{hidden}"
    two_valued = f"-bin{''.join(map(str, binary))}" if binary else ""
    seen_from_ee = "-rel" if relative else ""
    return f"bc-n{n}-s{seed}{average}{'' if steps == STEPS else f'-{steps}steps'}{width}{two_valued}{seen_from_ee}"


def train(data: Path, out: Path, seed: int, setting: Setting) -> Path:
    n, ema_decay, steps, hidden, binary, _ = setting
    flags = [
        "--policy.type=iupe", "--policy.supervised=true", f"--policy.n_obs_steps={n}", f"--batch_size={BATCH}",
        f"--seed={seed}", "--log_freq=500", f"--policy.ema_decay={ema_decay}", f"--policy.hidden_dim={hidden}",
        f"--policy.binary_action_dims=[{','.join(map(str, binary))}]",
    ]  # fmt: skip
    return train_once(data, out, *flags, steps=steps)


def setting(row: dict) -> Setting:
    """Rows measured before an option existed are its default's."""
    return Setting(
        row["n_obs_steps"], row.get("ema_decay", 0.0), row.get("steps", STEPS), row.get("hidden_dim", HIDDEN),
        tuple(row.get("binary_action_dims", ())), row.get("relative_positions", False),
    )  # fmt: skip


def command_key(key: Setting) -> str:
    """history.json's key of a setting's command; settings at the later options' defaults keep their first keys."""
    return str(tuple(key) if key.binary_action_dims or key.relative_positions else tuple(key[:4]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ns", nargs="+", type=int, default=[1, 4])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--jobs", type=int, default=2, help="trainings at once, one thread each")
    parser.add_argument("--ema_decay", type=float, default=0.0, help="--policy.ema_decay of every run (0: none)")
    parser.add_argument("--steps", type=int, default=STEPS, help="lerobot-train --steps of every run")
    parser.add_argument("--hidden_dim", type=int, default=HIDDEN, help="--policy.hidden_dim of every run")
    parser.add_argument(
        "--binary_action_dims", nargs="*", type=int, default=[], help="--policy.binary_action_dims of every run"
    )
    parser.add_argument("--relative_positions", action="store_true", help="--env.relative_positions=true")
    parser.add_argument("--work", default="outputs/measure-history")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    env = ENV | ({"relative_positions": True} if args.relative_positions else {})
    data = work / f"so101-expert-actions{'-rel' if args.relative_positions else ''}"
    if not (data / "meta" / "info.json").exists():
        run_cli(
            "lerobot-iupe-collect", *env_cli_flags(env), "--agent=expert",
            f"--episodes={EPISODES}", "--seed=0", "--keep_actions=true", f"--dataset.repo_id=local/{data.name}",
            f"--dataset.root={data}", "--overwrite=true",
        )  # fmt: skip
    runs = [
        (seed, Setting(n, args.ema_decay, args.steps, args.hidden_dim, tuple(args.binary_action_dims),
                       args.relative_positions))
        for n in args.ns for seed in args.seeds
    ]  # fmt: skip
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        checkpoints = list(pool.map(lambda r: train(data, work / run_name(*r), *r), runs))
    env_cfg = env_config_from_settings(env)
    rows = []
    for (seed, run_setting), checkpoint in zip(runs, checkpoints, strict=True):
        overall = evaluate_checkpoint(checkpoint, env_cfg, EVAL_EPISODES, "argmax")
        success = overall["pc_success"] / 100
        fields = run_setting._asdict()
        rows.append({**fields, "binary_action_dims": list(run_setting.binary_action_dims), "seed": seed,
                     "success": success})  # fmt: skip
        print(rows[-1], flush=True)
    command = command_line()
    commands = {}
    if (out / "history.json").exists():  # rows of other settings stay, with their own command
        before = json.loads((out / "history.json").read_text())
        new = {setting(r) for r in rows}
        kept = [r for r in before["rows"] if setting(r) not in new]
        # a page from before per-setting commands has one command for all its rows
        recorded = before.get("commands") or {command_key(setting(r)): before["command"] for r in kept}
        commands = {command_key(setting(r)): recorded[command_key(setting(r))] for r in kept}
        rows = kept + rows
    commands.update({command_key(setting(r)): command for r in rows if command_key(setting(r)) not in commands})
    table = [
        "| n_obs_steps | weight average (ema_decay) | steps | hidden_dim | binary action dims | relative positions "
        "| success per seed | mean ± std (ddof 1) | command |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in sorted({setting(r) for r in rows}):
        success = np.array([r["success"] for r in rows if setting(r) == key])
        spread = f" ± {success.std(ddof=1):.2f}" if len(success) > 1 else ""
        table.append(
            f"| {key.n_obs_steps} | {key.ema_decay or 'none'} | {key.steps} | {key.hidden_dim} | "
            f"{list(key.binary_action_dims) or 'none'} | {'yes' if key.relative_positions else 'no'} | "
            f"{' / '.join(f'{s:.2f}' for s in success)} | {success.mean():.2f}{spread} | "
            f"`{commands[command_key(key)]}` |"
        )
    intro = (
        f"BC on {EPISODES} scripted-expert episodes' true actions (batch {BATCH}), success over {EVAL_EPISODES} "
        f"episodes (seeds 500000…, cap {env_cfg.episode_length}) by the policy's mode, as `lerobot-eval` plays it "
        "by default; every setting on the same data and evaluation episodes."
    )
    title = "Policies that remember: BC on SO-101 pick-and-place with an observation history"
    write_page(out, "history", command, rows, title, intro, table)
    page = json.loads((out / "history.json").read_text())
    (out / "history.json").write_text(json.dumps({**page, "commands": commands}, indent=1) + "\n")


if __name__ == "__main__":
    main()
