"""lerobot-iupe-benchmark: the paper's Table 1 (Expert, Random, BC, BCO(α), IUPE, ILPO on CartPole, Acrobot,
MountainCar, Maze 3×3/5×5/10×10), its Table 2 (the ablation on Maze 10×10), a low-data table, continuous actions
(LunarLander, SO-101) and Meta-World's MT10 (LeRobot's own Meta-World env, observed as state).

Each trained method goes through `lerobot-train`; evaluation is LeRobot's own (`eval_policy_all`, as in
`lerobot-eval`) on seeds never used in training. Runs are recorded as they finish in <work>/runs.jsonl, so an
interrupted benchmark resumes; <out>/results.md, results.json and the PNG plots are rebuilt at the end.

Examples:
    lerobot-iupe-benchmark                                  # Table 1, 3 seeds, 100 evaluation episodes
    lerobot-iupe-benchmark --tables table1 ablation lowdata
    lerobot-iupe-benchmark --envs cartpole acrobot --seeds 0 1 2
    lerobot-iupe-benchmark --tables table1 --jobs 2         # two runs at a time, one thread each
    lerobot-iupe-benchmark --tables metaworld --envs mw-push mw-reach --methods bc bco iupe ilpo \
        --eval_episodes 50 --jobs 2 --work outputs/metaworld --out benchmarks/metaworld
    lerobot-iupe-benchmark --quick                          # smoke test: CartPole + Maze 3×3, tiny budgets
    lerobot-iupe-benchmark --tables ablation --from benchmarks   # fresh clone: train only what results.json lacks
"""

import argparse
import shlex
import sys
import time
from pathlib import Path

from lerobot_iupe.benchmark import (
    ABLATION,
    CONTINUOUS,
    LOW_DATA,
    LOW_DATA_METHODS,
    METAWORLD,
    PRESETS,
    TABLE1_METHODS,
    Benchmark,
    write_report,
)

METHODS = TABLE1_METHODS


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be 1 or more (runs trained at once), got {value}")
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--tables", nargs="+", default=["table1"],
        choices=["table1", "ablation", "lowdata", "continuous", "metaworld"],
        help="continuous: LunarLander and SO-101 (all Table 1 methods; SO-101 from uniformly random "
        "pre-demonstrations, so101_uniform: BCO(α) and IUPE) and LunarLander's low-data row; metaworld: MT10's ten "
        "tasks (mw-push, …) observed as state, 10 expert demonstrations each, success by the mode",
    )  # fmt: skip
    parser.add_argument(
        "--envs", nargs="+", default=[*PRESETS, *CONTINUOUS, *METAWORLD], choices=[*PRESETS, *CONTINUOUS, *METAWORLD],
        help="envs of every table (each table runs those of its own among them)",
    )  # fmt: skip
    parser.add_argument(
        "--methods", nargs="+", choices=METHODS,
        help=f"methods of Table 1, the continuous and the metaworld tables (default: {' '.join(METHODS)}; the "
        "continuous and metaworld tables run ILPO (ilpo: as the authors' code; ilpo_norm: with "
        "--policy.normalize=true) only when named here)",
    )  # fmt: skip
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="training seeds per cell")
    parser.add_argument(
        "--jobs", type=positive_int, default=1,
        help="runs trained at once, one CPU thread each (2 on a 2-core machine: about half the wall-clock)",
    )  # fmt: skip
    parser.add_argument("--eval_episodes", type=int, default=100)
    parser.add_argument("--quick", action="store_true", help="CartPole + Maze 3×3, 1 seed, 10 episodes, tiny runs")
    parser.add_argument("--work", default="outputs/benchmark", help="datasets, runs and runs.jsonl")
    parser.add_argument("--out", default="benchmarks", help="where results.md/json and the plots go")
    parser.add_argument(
        "--from", dest="from_dir", metavar="DIR",
        help="first add the runs and calls of a committed report (DIR/results.json, DIR/calls.json) to --work, so "
        "only runs missing from it are trained (e.g. --from=benchmarks on a fresh clone)",
    )  # fmt: skip
    parser.add_argument(
        "--rerun", action="store_true",
        help="train and evaluate the selected runs again even where --work (or --from) records them: after a change "
        "to a learner, whose runs' configuration is otherwise unchanged; their old records are dropped",
    )  # fmt: skip
    args = parser.parse_args()
    continuous_methods = args.methods or [m for m in METHODS if not m.startswith("ilpo")]
    args.methods = args.methods or METHODS
    if args.from_dir and not (Path(args.from_dir) / "results.json").exists():
        parser.error(f"--from: {args.from_dir} holds no results.json (a benchmark call's --out, e.g. benchmarks)")
    if args.quick:
        args.envs = [e for e in args.envs if e in ("cartpole", "maze3")] or ["cartpole"]
        args.seeds, args.eval_episodes = args.seeds[:1], min(args.eval_episodes, 10)
    start = time.perf_counter()
    bench = Benchmark(Path(args.work), eval_episodes=args.eval_episodes, quick=args.quick)
    try:
        if args.from_dir:
            added = bench.seed_from(Path(args.from_dir))
            print(f"[benchmark] {added} records added from {args.from_dir}/results.json", flush=True)
        requests = []
        if "table1" in args.tables:
            for env in (e for e in args.envs if e in PRESETS):
                requests.append(dict(table="table1", name=env, preset=PRESETS[env], methods=args.methods))
        if "lowdata" in args.tables:
            for env, preset in LOW_DATA.items():
                if env not in CONTINUOUS and env in args.envs:
                    requests.append(dict(table="lowdata", name=env, preset=preset, methods=LOW_DATA_METHODS))
        if "continuous" in args.tables:
            for env, preset in CONTINUOUS.items():
                if env in args.envs:
                    methods = preset.compared(continuous_methods)
                    requests.append(dict(table="continuous", name=env, preset=preset, methods=methods))
            for env in (e for e in LOW_DATA if e in CONTINUOUS and e in args.envs):
                preset = LOW_DATA[env]
                methods = preset.compared(continuous_methods)
                requests.append(dict(table="lowdata", name=env, preset=preset, methods=methods))
        if "metaworld" in args.tables:
            for env in (e for e in METAWORLD if e in args.envs):
                requests.append(dict(table="metaworld", name=env, preset=METAWORLD[env], methods=continuous_methods))
        if "ablation" in args.tables:
            # BCO(α) and IUPE are Table 1's Maze 10×10 runs (same data, preset and seeds): run or reuse them.
            requests.append(dict(table="table1", name="maze10", preset=PRESETS["maze10"], methods=["bco", "iupe"]))
            variants = [v for v in ABLATION if v not in ("bco", "iupe")]
            requests.append(dict(table="ablation", name="maze10", preset=PRESETS["maze10"], methods=variants))
        if args.rerun:
            dropped = bench.forget(
                [(r["table"], r["name"], m, s) for r in requests for m in r["methods"] for s in [*args.seeds, None]]
            )
            print(f"[benchmark] --rerun: {dropped} recorded rows dropped", flush=True)
        runs = bench.plan_all([{**request, "seeds": args.seeds} for request in requests], jobs=args.jobs)
        unique = {(run.table, run.name, run.method, run.seed): run for run in runs}
        bench.execute(list(unique.values()), jobs=args.jobs)
    except RuntimeError as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(1)
    finally:
        calls = bench.log_call(shlex.join(["lerobot-iupe-benchmark", *sys.argv[1:]]), time.perf_counter() - start)
        records = bench.records()
        if records:
            paths = write_report(records, Path(args.out), calls)
            print("\n".join(["wrote:", *map(str, paths)]))


if __name__ == "__main__":
    main()
