"""Wall-clock of a Table 1 vector run against a plain torch loop on the same data.

The package's side is the benchmark's own run (`lerobot-iupe-benchmark --tables table1 --envs cartpole acrobot
mountaincar --methods bc bco iupe --seeds 0 --jobs 1`): `lerobot-train` with the preset's flags, one thread, timed
from its start to its exit, with LeRobot's per-step frame-loading time (its log's `data_s`) and the cycle's own IDM
and rollout seconds. The plain side reads the same expert parquet files with pyarrow into tensors and trains a
2×256 MLP by cross-entropy on the true actions with Adam, the preset's steps, batch size and learning rate, one
thread, in a fresh interpreter timed from outside (its start and imports included, as lerobot-train's are).
For BCO(α) and IUPE the plain figure adds the run's own IDM and rollout seconds to the plain BC loop: the work a
plain loop of the same cycle could not skip.

    python benchmarks/measure/overhead.py [--envs cartpole acrobot mountaincar] [--repeats 3]

Writes benchmarks/overhead.json and benchmarks/overhead.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

METHODS = ("bc", "bco", "iupe")


def plain_loop(root: Path, steps: int, batch: int, lr: float, seed: int) -> None:
    """BC as a plain loop: the whole dataset in two tensors, index a random batch, step."""
    import pyarrow.parquet as pq
    import torch

    torch.set_num_threads(1)
    torch.manual_seed(seed)
    table = pq.read_table(sorted((root / "data").glob("*/*.parquet")), columns=["observation.state", "action"])
    states = torch.tensor(table.column("observation.state").to_pylist(), dtype=torch.float32)
    actions = torch.tensor(table.column("action").to_pylist()).reshape(len(states), -1)[:, 0].long()
    states = (states - states.mean(0)) / (states.std(0) + 1e-6)
    net = torch.nn.Sequential(
        torch.nn.Linear(states.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
        torch.nn.Linear(256, int(actions.max()) + 1),
    )  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), lr)
    for _ in range(steps):
        rows = torch.randint(len(states), (batch,))
        loss = torch.nn.functional.cross_entropy(net(states[rows]), actions[rows])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def timed(command: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["cartpole", "acrobot", "mountaincar"])
    parser.add_argument("--repeats", type=int, default=3, help="plain loops per env (their median is kept)")
    parser.add_argument("--work", default="outputs/measure-overhead", help="the benchmark call's --work")
    parser.add_argument("--out", default="benchmarks")
    parser.add_argument("--plain", nargs=5, metavar=("ROOT", "STEPS", "BATCH", "LR", "SEED"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.plain:
        root, steps, batch, lr, seed = args.plain
        plain_loop(Path(root), int(steps), int(batch), float(lr), int(seed))
        return

    from lerobot_iupe.benchmark.presets import PRESETS
    from lerobot_iupe.benchmark.runner import run_cli

    work = Path(args.work)
    benchmark = [
        "lerobot-iupe-benchmark", "--tables", "table1", "--envs", *args.envs, "--methods", *METHODS, "--seeds", "0",
        "--jobs", "1", "--work", str(work), "--out", str(work / "report"),
    ]  # fmt: skip
    records = work / "runs.jsonl"
    done = (
        {(r["env"], r["method"]) for r in map(json.loads, records.read_text().splitlines())}
        if records.exists()
        else set()
    )
    if any((env, method) not in done for env in args.envs for method in METHODS):
        run_cli(*benchmark)
    runs = {}
    for record in map(json.loads, records.read_text().splitlines()):
        runs[record["env"], record["method"]] = record  # both evaluation rules carry the same training figures
    start_up = timed([str(Path(sys.executable).parent / "lerobot-train"), "--help"])
    rows = []
    for env in args.envs:
        preset = PRESETS[env]
        budget = preset.train
        lr = float(budget.policy.get("optimizer_lr", "1e-3"))
        data = next((work / "data").glob(f"{env}-*-expert-actions"))
        command = [
            sys.executable,
            __file__,
            "--plain",
            str(data),
            str(budget.steps),
            str(budget.batch_size),
            str(lr),
            "0",
        ]
        plain = sorted(timed(command) for _ in range(args.repeats))[args.repeats // 2]
        for method in METHODS:
            run = runs[env, method]
            timing = run["timing"]
            cycle = timing.get("idm_s", 0.0) + timing.get("rollouts_s", 0.0)
            rows.append({
                "env": env, "method": method, "steps": budget.steps, "batch_size": budget.batch_size,
                "package_s": run["train_seconds"], "frame_loading_s": timing["data_loading_s"],
                "idm_and_rollouts_s": cycle, "lerobot_train_start_s": start_up, "plain_bc_s": plain,
                "plain_equivalent_s": plain + cycle, "ratio": run["train_seconds"] / (plain + cycle),
                "ratio_without_frame_loading": (run["train_seconds"] - timing["data_loading_s"]) / (plain + cycle),
            })  # fmt: skip
    out = Path(args.out)
    (out / "overhead.json").write_text(json.dumps({"command": " ".join(benchmark), "rows": rows}, indent=1) + "\n")
    lines = [
        "# Wall-clock of a vector run against a plain torch loop",
        "",
        f"`{' '.join(['python', 'benchmarks/measure/overhead.py', *sys.argv[1:]])}` (the package's runs by "
        f"`{' '.join(benchmark)}`). How each side is timed: the script's docstring. Seconds, one thread each.",
        "",
        "| env | method | steps × batch | package run | LeRobot frame loading | lerobot-train start | IDM + rollouts "
        "| plain loop (BC + the run's IDM and rollouts) | package / plain | the same without LeRobot's frame loading |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['env']} | {r['method']} | {r['steps']} × {r['batch_size']} | {r['package_s']:.1f} | "
            f"{r['frame_loading_s']:.1f} | {r['lerobot_train_start_s']:.1f} | {r['idm_and_rollouts_s']:.1f} | "
            f"{r['plain_equivalent_s']:.1f} | {r['ratio']:.1f}× | {r['ratio_without_frame_loading']:.1f}× |"
        )
    (out / "overhead.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
