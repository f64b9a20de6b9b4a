"""Measure lerobot-iupe-relabel: label accuracy against the true actions, and throughput beside the plain decode
rate of the same video. Writes benchmarks/relabel.md and benchmarks/relabel.json.

    python scripts/measure_relabel.py
Checkpoints come from normal training runs: the benchmark's (IUPE, seed 0) or `python scripts/demo.py --env <env>`.
Expert data for the accuracy check is collected on seeds 700000… (never used in training), with its actions,
then stripped of them with LeRobot's `remove_feature`, relabelled, and compared on every frame with a successor.
"""

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.datasets.dataset_tools import remove_feature

from lerobot_iupe.benchmark import CHECKPOINT
from lerobot_iupe.data.readers import video_chunks
from lerobot_iupe.data.storage import read_iupe_meta, write_iupe_meta

BIN = Path(sys.executable).parent
ENVS = {  # demo preset -> collect flags
    "cartpole": ["--env.type=cartpole"],
    "mountaincar": ["--env.type=mountaincar"],
    "acrobot": ["--env.type=acrobot"],
    "maze5": ["--env.type=maze", "--env.size=5"],
}


def run(*args: str) -> str:
    print("$", " ".join(args), flush=True)
    result = subprocess.run([str(BIN / args[0]), *args[1:]], check=True, capture_output=True, text=True)
    return result.stdout


def checkpoint_of(env: str) -> Path:
    """The IUPE seed-0 checkpoint of the benchmark's Table 1 run if there is one, else a demo run's (trained now
    when missing)."""
    benchmark = Path("outputs/benchmark/runs/table1") / env / "iupe-s0" / CHECKPOINT
    if benchmark.exists():
        return benchmark
    out = Path("outputs/demo" if env == "cartpole" else f"outputs/demo-{env}")
    checkpoint = out / "runs/demo" / env / "iupe-s0" / CHECKPOINT
    if not checkpoint.exists():
        subprocess.run([sys.executable, "scripts/demo.py", "--env", env], check=True)
    return checkpoint


def actions_with_successor(root: Path) -> np.ndarray:
    table = LeRobotDataset("local/m", root=root, video_backend="pyav").hf_dataset.with_format("numpy")
    episodes = np.asarray(table["episode_index"])
    return np.asarray(table["action"]).reshape(-1)[np.append(episodes[:-1] == episodes[1:], False)]


def accuracy(env: str, work: Path, episodes: int) -> dict:
    truth, stripped = work / f"{env}-truth", work / f"{env}-stripped"
    run(
        "lerobot-iupe-collect", *ENVS[env], "--agent=expert", f"--episodes={episodes}", "--seed=700000",
        "--keep_actions=true", f"--dataset.repo_id=local/{truth.name}", f"--dataset.root={truth}",
    )  # fmt: skip
    source = LeRobotDataset(f"local/{truth.name}", root=truth, video_backend="pyav")
    remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
    write_iupe_meta(stripped, {**read_iupe_meta(truth), "has_actions": False})
    checkpoint = checkpoint_of(env)
    start = time.perf_counter()
    run(
        "lerobot-iupe-relabel", f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{stripped.name}",
        f"--dataset.root={stripped}", "--video_backend=pyav",
    )  # fmt: skip
    seconds = time.perf_counter() - start
    true, labelled = actions_with_successor(truth), actions_with_successor(stripped)
    return {
        "env": env,
        "checkpoint": str(checkpoint),
        "episodes": episodes,
        "frames_compared": int(len(true)),
        "agreement": float((true == labelled).mean()),
        "cli_seconds": seconds,
    }


def relabel_rate(checkpoint: Path, root: Path, batch_size: int) -> float:
    """Frames/s of the relabel pass itself, as the CLI reports it (dry run: labelling without writing)."""
    out = run(
        "lerobot-iupe-relabel", f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{root.name}",
        f"--dataset.root={root}", "--dry_run=true", "--video_backend=pyav", f"--batch_size={batch_size}",
    )  # fmt: skip
    line = next(line for line in out.splitlines() if "frames/s" in line)
    return float(line.split("(")[-1].split(" frames/s")[0])


def decode_rate(root: Path, batch_size: int) -> float:
    meta = LeRobotDatasetMetadata("local/d", root=root)
    start = time.perf_counter()
    chunks = video_chunks(meta, "observation.image", batch_size, "pyav")
    frames = sum(len(c.frames) - 1 + c.ends_episode for c in chunks)
    return frames / (time.perf_counter() - start)


def throughput(work: Path, batch_size: int) -> list[dict]:
    rows = []
    vector = work / "cartpole-throughput"
    run(
        "lerobot-iupe-collect", "--env.type=cartpole", "--agent=expert", "--episodes=100", "--seed=710000",
        f"--dataset.repo_id=local/{vector.name}", f"--dataset.root={vector}",
    )  # fmt: skip
    frames = LeRobotDatasetMetadata("local/v", root=vector).total_frames
    rows.append(
        {"dataset": f"CartPole state, {frames} frames", "relabel_fps": relabel_rate(checkpoint_of("cartpole"), vector,
         batch_size), "decode_fps": None}
    )  # fmt: skip
    video = work / "maze5-throughput"
    run(
        "lerobot-iupe-collect", "--env.type=maze", "--env.size=5", "--agent=random", "--random_start=true",
        "--episodes=200", "--seed=720000", f"--dataset.repo_id=local/{video.name}", f"--dataset.root={video}",
    )  # fmt: skip
    frames = LeRobotDatasetMetadata("local/v", root=video).total_frames
    rows.append(
        {
            "dataset": f"Maze 5×5 64×64 AV1 video (pyav), {frames} frames",
            "relabel_fps": relabel_rate(checkpoint_of("maze5"), video, batch_size),
            "decode_fps": decode_rate(video, batch_size),
        }
    )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50, help="expert episodes per env for the accuracy check")
    parser.add_argument("--batch_size", type=int, default=512)
    parser.add_argument("--work", default="outputs/measure-relabel")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    accuracies = [accuracy(env, work, args.episodes) for env in ENVS]
    rates = throughput(work, args.batch_size)
    command = " ".join(["python", "scripts/measure_relabel.py", *sys.argv[1:]])
    lines = [
        "# lerobot-iupe-relabel: measured",
        "",
        f"Produced by `{command}` on a 2-core CPU (no GPU). Checkpoints: "
        + ", ".join(f"{env} `{checkpoint_of(env)}`" for env in ENVS)
        + ".",
        "",
        "## Label accuracy (expert data on unseen seeds, true actions stripped, relabelled, compared)",
        "",
        "| env | episodes | frames compared | agreement |",
        "|---|---|---|---|",
        *[f"| {a['env']} | {a['episodes']} | {a['frames_compared']} | {a['agreement']:.4f} |" for a in accuracies],
        "",
        f"## Throughput (batch {args.batch_size}, CPU)",
        "",
        "| dataset | relabel frames/s | plain decode frames/s | ratio |",
        "|---|---|---|---|",
    ]
    for r in rates:
        decode = f"{r['decode_fps']:.0f}" if r["decode_fps"] else "–"
        ratio = f"{r['relabel_fps'] / r['decode_fps']:.2f}" if r["decode_fps"] else "–"
        lines.append(f"| {r['dataset']} | {r['relabel_fps']:.0f} | {decode} | {ratio} |")
    out = Path(args.out)
    out.mkdir(exist_ok=True)
    (out / "relabel.md").write_text("\n".join(lines) + "\n")
    (out / "relabel.json").write_text(json.dumps({"command": command, "accuracy": accuracies, "throughput": rates},
                                                 indent=2) + "\n")  # fmt: skip
    print("\n".join(lines))


if __name__ == "__main__":
    main()
