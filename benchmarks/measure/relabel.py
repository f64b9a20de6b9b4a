"""Label accuracy of the IDMs of full IUPE runs against the true actions. Writes the "accuracy" section of
benchmarks/relabel.json and renders benchmarks/relabel.md (throughput: benchmarks/measure/throughput.py).

    python benchmarks/measure/relabel.py [--envs cartpole mountaincar acrobot maze5]
Each checkpoint is trained here, exactly as the benchmark's Table 1 IUPE seed-0 run (its preset, datasets and
budget), with today's code. Expert data for the accuracy check is collected with the preset's env settings on
seeds 700000… (never used in training), with its actions, then stripped of them with LeRobot's `remove_feature`,
relabelled, and compared on every frame with a successor.
"""

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path

from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_tools import remove_feature

from lerobot_iupe.benchmark import CHECKPOINT, PRESETS, Benchmark
from lerobot_iupe.data.storage import read_iupe_meta, write_iupe_meta

BIN = Path(sys.executable).parent
sys.path.insert(0, str(Path(__file__).parent))
from relabel_report import render, update  # noqa: E402
from run_labels import actions_with_successor  # noqa: E402
from steps import command_line  # noqa: E402

ENVS = ["cartpole", "mountaincar", "acrobot", "maze5"]


def run(*args: str) -> str:
    print("$", " ".join(args), flush=True)
    result = subprocess.run([str(BIN / args[0]), *args[1:]], check=True, capture_output=True, text=True)
    return result.stdout


def checkpoint_of(env: str, work: Path) -> Path:
    """The benchmark's Table 1 IUPE seed-0 run of ``env``, trained in ``work`` (kept there: a second call reuses it;
    its 10-episode evaluation is not used here)."""
    bench = Benchmark(work, eval_episodes=10, quiet=True)
    bench.execute(bench.plan("table1", env, PRESETS[env], ["iupe"], [0]))
    return work / "runs" / "table1" / env / "iupe-s0" / CHECKPOINT


def accuracy(env: str, work: Path, episodes: int) -> dict:
    truth, stripped = work / f"{env}-truth", work / f"{env}-stripped"
    shutil.rmtree(truth, ignore_errors=True)
    shutil.rmtree(stripped, ignore_errors=True)
    run(
        "lerobot-iupe-collect", *PRESETS[env].env_flags(), "--agent=expert", f"--episodes={episodes}", "--seed=700000",
        *PRESETS[env].data.data_flags(),
        "--keep_actions=true", f"--dataset.repo_id=local/{truth.name}", f"--dataset.root={truth}",
    )  # fmt: skip
    source = LeRobotDataset(f"local/{truth.name}", root=truth, video_backend="pyav")
    remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
    write_iupe_meta(stripped, {**read_iupe_meta(truth), "has_actions": False})
    checkpoint = checkpoint_of(env, work / "benchmark")
    start = time.perf_counter()
    run(
        "lerobot-iupe-relabel", f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{stripped.name}",
        f"--dataset.root={stripped}", "--dataset.video_backend=pyav",
    )  # fmt: skip
    seconds = time.perf_counter() - start
    true, labelled = (actions_with_successor(f"local/{root.name}", root) for root in (truth, stripped))
    return {
        "env": env,
        "checkpoint": str(checkpoint),
        "episodes": episodes,
        "frames_compared": int(len(true)),
        "agreement": float((true == labelled).mean()),
        "cli_seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50, help="expert episodes per env for the accuracy check")
    parser.add_argument("--envs", nargs="+", default=ENVS, choices=ENVS)
    parser.add_argument("--work", default="outputs/measure-relabel")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    accuracies = [accuracy(env, work, args.episodes) for env in args.envs]
    command = command_line()
    update(Path(args.out), "accuracy", accuracies, command, key=("env",))
    print(render(Path(args.out)))


if __name__ == "__main__":
    main()
