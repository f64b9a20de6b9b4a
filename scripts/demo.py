"""`make demo`: the main job on an embedded default — local CartPole data, CPU, no hub.

1. `lerobot-iupe-collect`: a state-only expert dataset and random pre-demonstrations.
2. `lerobot-train --policy.type=iupe`: the full IUPE algorithm.
3. Evaluation with LeRobot's own code (what `lerobot-eval` runs) on seeds never used in training
   (mazes: on the demonstration layouts and on held-out layouts).
4. P and AER against the expert demonstrations and a uniform-random policy; a plot of the training cycles.

    python scripts/demo.py                      # CartPole, the `make demo` default
    python scripts/demo.py --env mountaincar    # also: acrobot, maze3, maze5, maze10
    python scripts/demo.py --env lunarlander    # continuous actions (also: so101_pickplace)
    python scripts/demo.py --method ilpo        # ILPO, the paper's other baseline (no pre-demonstrations)
The same code path as `lerobot-iupe-benchmark` (one run of seed 0), quiet: one line per stage and a progress
bar while training; every command's full output is in a log file under the output folder.
"""

import argparse
import logging
import shutil
import time
from pathlib import Path

from lerobot_iupe.benchmark import CHECKPOINT, CONTINUOUS, PRESETS, Benchmark, write_report

ENVS = {**PRESETS, **CONTINUOUS}
METHODS = {"iupe": "IUPE", "ilpo": "ILPO"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=sorted(ENVS), default="cartpole")
    parser.add_argument("--method", choices=sorted(METHODS), default="iupe", help="the learner to train")
    parser.add_argument("--eval_episodes", type=int, default=50)
    args = parser.parse_args()
    logging.disable(logging.WARNING)  # LeRobot's evaluation logs each batch; the table below says it all
    name = METHODS[args.method]
    suffix = "".join(f"-{part}" for part in (args.env, args.method) if part not in ("cartpole", "iupe"))
    out = Path(f"outputs/demo{suffix}")
    shutil.rmtree(out, ignore_errors=True)
    bench = Benchmark(out, eval_episodes=args.eval_episodes, quiet=True)
    preset = ENVS[args.env]
    start = time.perf_counter()
    print(f"[1/3] collecting the {args.env} datasets (expert without actions, random pre-demonstrations)", flush=True)
    runs = bench.plan("demo", args.env, preset, [args.method], [0])
    print(f"      datasets in {out / 'data'} ({time.perf_counter() - start:.0f}s)", flush=True)
    steps = runs[0].steps if runs else preset.train.steps
    print(f"[2/3] training {name} with lerobot-train ({steps} steps), then evaluating", flush=True)
    bench.execute(runs)
    command = f"python scripts/demo.py --env {args.env} --method {args.method}"
    calls = bench.log_call(command, time.perf_counter() - start)
    records = bench.records()
    written = write_report(records, out, calls)
    print(f"[3/3] evaluated on {args.eval_episodes} episodes per setting, seeds never used in training\n")
    print("| method | env | eval layouts | eval mode | P | AER | success | train s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in records:
        print(
            f"| {name} | {r['env']} | {r['eval_layouts'] or '–'} | {r['eval_mode']} | {r['P']:.3f} | {r['AER']:.3f} "
            f"| {r['success_rate']:.0%} | {r['train_seconds']:.0f} |"
        )
    print(
        f"\nreferences (the built-in expert and a uniform-random agent on the same episodes): "
        f"expert {records[0]['R_expert']:.3f}, random {records[0]['R_random']:.3f}"
    )
    print(f"checkpoint: {out / 'runs' / 'demo' / args.env / f'{args.method}-s0' / CHECKPOINT}")
    plots = [str(p) for p in written if p.suffix == ".png"]  # ILPO has no training cycles to plot
    print(f"report: {out / 'results.md'}" + (f"   plots: {'  '.join(plots)}" if plots else ""))
    run_logs = out / "runs" / "demo" / args.env
    logs = f"{run_logs}/{args.method}-s0.log (training), {args.method}-s0.eval.log (evaluation)"
    print(f"logs: {logs}, {out / 'data' / 'logs'} (datasets)")
    print(f"total: {time.perf_counter() - start:.0f}s")


if __name__ == "__main__":
    main()
