"""How LunarLander episodes end under trained policies: the evaluation episodes of `downstream.py` (seeds 500000…,
50 of them) played again by each checkpoint, each end sorted into a safe landing (the success `lerobot-eval`
counts), at rest but not landed (beside the pad, or between its flags without both legs down), crashed (Box2D's
game over or off the screen) or out of time (1,000 steps), with where the lander ended (|x|, the pad's flags at 0.2;
over every episode and over those at rest but not landed alone, which tells a lander beside the pad from one between
the flags) and how often each engine fired.

    python benchmarks/measure/lunar_outcomes.py --work /tmp/w/dl-lun --runs 'lunarlander-act-*-replan-3000'

Writes benchmarks/lunar_outcomes.json and .md; a run already on the page is replaced, others are kept with the
commands that measured them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.envs.utils import preprocess_observation

from lerobot_iupe.benchmark.evaluation import load_checkpoint
from lerobot_iupe.envs.lunar import LunarLanderEnv

sys.path.insert(0, str(Path(__file__).parent))
from steps import CHECKPOINT, command_line, read_page, write_page  # noqa: E402

EVAL_SEED, EPISODES, MAX_STEPS = 500_000, 50, 1000
ENDS = ("landed", "at rest, not landed", "crashed", "out of time")


def median_or_none(values: list[float]) -> float | None:
    return float(np.median(values)) if values else None


def play(checkpoint: Path, meta, episodes: int = EPISODES) -> dict:
    """Each episode's end (``ENDS``), the lander's final |x| (median over all episodes and over those at rest but not
    landed; None where there are none), and the share of steps each engine fired."""
    _, policy, preprocessor, postprocessor = load_checkpoint(checkpoint, ds_meta=meta)
    env = gym.wrappers.TimeLimit(LunarLanderEnv(render_mode=None), MAX_STEPS)
    ends, final_x, fired = [], [], []
    for index in range(episodes):
        observation, _ = env.reset(seed=EVAL_SEED + index)
        policy.reset()
        while True:
            batch = {**preprocess_observation(observation), "task": [""]}  # as lerobot-eval reads the env
            with torch.no_grad():
                action = postprocessor(policy.select_action(preprocessor(batch)))[0].numpy()
            fired.append((action[0] > 0, abs(action[1]) > 0.5))
            observation, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        at_rest = terminated and not env.unwrapped.lander.awake
        ends.append(ENDS[0] if info["is_success"] else ENDS[1] if at_rest else ENDS[2] if terminated else ENDS[3])
        final_x.append(abs(float(observation["agent_pos"][0])))
    return {
        "ends": {end: ends.count(end) for end in ENDS},
        "success_rate": ends.count(ENDS[0]) / episodes,
        "final_abs_x_median": float(np.median(final_x)),
        "not_landed_at_rest_abs_x_median": median_or_none(
            [x for x, end in zip(final_x, ends, strict=True) if end == ENDS[1]]
        ),
        "engines_fired": np.mean(fired, axis=0).round(3).tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--runs", nargs="+", required=True, help="run folders in --work (glob patterns)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    truth = args.work / "lunarlander-true"
    meta = LeRobotDataset(f"local/{truth.name}", root=truth).meta
    runs = sorted({run for pattern in args.runs for run in args.work.glob(pattern) if (run / CHECKPOINT).exists()})
    before, commands = read_page(args.out, "lunar_outcomes")
    measured = []
    for run in runs:
        measured.append({"run": run.name, **play(run / CHECKPOINT, meta)})
        print(measured[-1], flush=True)
    names = {row["run"] for row in measured}
    rows = sorted([row for row in before if row["run"] not in names] + measured, key=lambda row: row["run"])
    write(args.out, rows, list(dict.fromkeys([*commands, command_line()])))


def write(out: Path, rows: list[dict], commands: list[str]) -> None:
    table = [f"| run | success | {' | '.join(ENDS)} | final \\|x\\| (median) | at rest, not landed: \\|x\\| "
             "(median) | main, side engine fired |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for row in rows:
        counts = " | ".join(str(row["ends"][end]) for end in ENDS)
        fired = ", ".join(f"{x:.3f}" for x in row["engines_fired"])
        at_rest_x = row["not_landed_at_rest_abs_x_median"]
        at_rest_x = "–" if at_rest_x is None else f"{at_rest_x:.2f}"
        table.append(
            f"| {row['run']} | {row['success_rate']:.2f} | {counts} | {row['final_abs_x_median']:.2f} | {at_rest_x} | "
            f"{fired} |"
        )
    write_page(out, "lunar_outcomes", commands, rows, "How LunarLander episodes end under trained policies",
               (__doc__ or "").split("\n\n")[0], table)  # fmt: skip


if __name__ == "__main__":
    main()
