"""Relabelling throughput on one process and on two (`torchrun --nproc_per_node=2`), against the plain decode rate
of the same video: a CartPole state dataset (100 expert episodes) and a Maze 5×5 64×64 AV1 video dataset (200
random episodes). The IDMs are `--policy.supervised=true` checkpoints of the package's default sizes (a few
steps: speed does not depend on the weights). Dry runs (labelling, gathering, no writing), PyAV decoding.

    python scripts/measure_throughput.py

Writes the "throughput" section of benchmarks/relabel.json and renders benchmarks/relabel.md.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from lerobot.datasets import LeRobotDatasetMetadata

from lerobot_iupe.data.readers import video_chunks

sys.path.insert(0, str(Path(__file__).parent))
from relabel_report import BIN, render, run, update  # noqa: E402

CHECKPOINT = "checkpoints/last/pretrained_model"


def prepare(work: Path, name: str, collect: list[str]) -> tuple[Path, Path]:
    root = work / name
    if not root.exists():
        run("lerobot-iupe-collect", *collect, f"--dataset.repo_id=local/{name}", f"--dataset.root={root}")
    out = work / f"{name}-idm"
    if not (out / CHECKPOINT).exists():
        run(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{name}",
            f"--dataset.root={root}", "--dataset.video_backend=pyav", f"--output_dir={out}", "--steps=4",
            "--save_freq=4", "--batch_size=8", "--num_workers=0", "--policy.device=cpu", "--wandb.enable=false",
        )  # fmt: skip
    return root, out / CHECKPOINT


def relabel_rate(checkpoint: Path, root: Path, processes: int, batch_size: int) -> float:
    """Frames/s of the labelling pass as the CLI reports it (dry run)."""
    command = [
        f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}",
        "--dry_run=true", "--dataset.video_backend=pyav", f"--batch_size={batch_size}",
    ]  # fmt: skip
    if processes > 1:
        out = run("torchrun", f"--nproc_per_node={processes}", "--standalone", str(BIN / "lerobot-iupe-relabel"),
                  *command)  # fmt: skip
    else:
        out = run("lerobot-iupe-relabel", *command)
    return float(re.search(r"\((\d+) frames/s\)", out).group(1))


def decode_rate(root: Path, batch_size: int) -> float:
    meta = LeRobotDatasetMetadata("local/d", root=root)
    start = time.perf_counter()
    frames = sum(
        len(c.frames) - 1 + c.ends_episode for c in video_chunks(meta, "observation.image", batch_size, "pyav")
    )
    return frames / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch_size", type=int, default=512)
    parser.add_argument("--work", default="outputs/measure-throughput")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    state, state_idm = prepare(
        work, "cartpole-100", ["--env.type=cartpole", "--agent=expert", "--episodes=100", "--seed=710000",
                               "--keep_actions=true"]
    )  # fmt: skip
    video, video_idm = prepare(
        work, "maze5-video-200", ["--env.type=maze", "--env.size=5", "--agent=random", "--random_start=true",
                                  "--episodes=200", "--seed=720000"]
    )  # fmt: skip
    rows = []
    state_frames = LeRobotDatasetMetadata("local/s", root=state).total_frames
    video_frames = LeRobotDatasetMetadata("local/v", root=video).total_frames
    decode = decode_rate(video, args.batch_size)
    for processes in (1, 2):
        rows.append(
            {
                "dataset": f"CartPole state, {state_frames} frames",
                "processes": processes,
                "relabel_fps": relabel_rate(state_idm, state, processes, args.batch_size),
                "decode_fps": None,
            }
        )
        rows.append(
            {
                "dataset": f"Maze 5×5 64×64 AV1 video (pyav), {video_frames} frames",
                "processes": processes,
                "relabel_fps": relabel_rate(video_idm, video, processes, args.batch_size),
                "decode_fps": decode,
            }
        )
        print(rows[-2:], flush=True)  # fmt: skip
    command = " ".join(["python", "scripts/measure_throughput.py", *sys.argv[1:]])
    update(Path(args.out), "throughput", rows, command)
    print(render(Path(args.out)))


if __name__ == "__main__":
    main()
