"""`make demo`: the main job on an embedded default — local CartPole data, CPU, no hub.

1. `lerobot-iupe-collect`: a state-only expert dataset and random pre-demonstrations.
2. `lerobot-train --policy.type=iupe`: the full IUPE algorithm.
3. Evaluation with LeRobot's own code (what `lerobot-eval` runs) on seeds never used in training
   (mazes: on the demonstration layouts and on held-out layouts).
4. P and AER against the expert demonstrations and a uniform-random policy; a plot of the training cycles.

    python scripts/demo.py                      # CartPole, the `make demo` default
    python scripts/demo.py --env mountaincar    # also: acrobot, maze3, maze5, maze10
The same code path as `lerobot-iupe-benchmark` (one IUPE run of seed 0). The checkpoint stays at
outputs/demo/runs/demo/<env>/iupe-s0/checkpoints/last/pretrained_model (outputs/demo-<env> for other envs).
"""

import argparse
import shutil
import time
from pathlib import Path

from lerobot_iupe.benchmark import CHECKPOINT, PRESETS, Benchmark, write_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=sorted(PRESETS), default="cartpole")
    parser.add_argument("--eval_episodes", type=int, default=50)
    args = parser.parse_args()
    out = Path("outputs/demo" if args.env == "cartpole" else f"outputs/demo-{args.env}")
    shutil.rmtree(out, ignore_errors=True)
    bench = Benchmark(out, eval_episodes=args.eval_episodes, echo=True)
    start = time.perf_counter()
    bench.run_env("demo", args.env, PRESETS[args.env], ["iupe"], [0])
    calls = bench.log_call(f"python scripts/demo.py --env {args.env}", time.perf_counter() - start)
    records = bench.records()
    write_report(records, out, calls)
    print("\n| method | env | eval layouts | eval mode | P | AER | success | train s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in records:
        print(
            f"| IUPE | {r['env']} | {r['eval_layouts'] or '–'} | {r['eval_mode']} | {r['P']:.3f} | {r['AER']:.3f} "
            f"| {r['success_rate']:.0%} | {r['train_seconds']:.0f} |"
        )
    print(f"references: expert {records[0]['R_expert']:.3f} (demonstrations), random {records[0]['R_random']:.3f}")
    print(f"checkpoint: {out / 'runs' / 'demo' / args.env / 'iupe-s0' / CHECKPOINT}")
    print(f"plot: {out / 'cycles.png'}   report: {out / 'results.md'}")


if __name__ == "__main__":
    main()
