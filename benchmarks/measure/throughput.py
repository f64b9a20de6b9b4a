"""Relabelling throughput on one process and on two (`torchrun --nproc_per_node=2`), against the plain decode rate
of the same video: a CartPole state dataset (100 expert episodes), a Maze 5×5 64×64 AV1 video dataset (200
random episodes) and the SO-101 arm seen by its front camera (64 px AV1 video) with its state (100 expert
episodes; the IDM reads both, fused). The IDMs are `--policy.supervised=true` checkpoints of the package's default
sizes (a few steps: speed does not depend on the weights). Dry runs (labelling, gathering, no writing), PyAV
decoding.

    python benchmarks/measure/throughput.py [--datasets cartpole maze5 so101_camera]

Writes the "throughput" section of benchmarks/relabel.json and renders benchmarks/relabel.md.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

from lerobot.datasets import LeRobotDatasetMetadata

from lerobot_iupe.data.episodes import episode_spans
from lerobot_iupe.data.video import CameraFrames

sys.path.insert(0, str(Path(__file__).parent))
from relabel_report import render, update  # noqa: E402
from steps import BIN, command_line, run  # noqa: E402

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


def decode_rate(meta: LeRobotDatasetMetadata, batch_size: int) -> float:
    """Frames/s of decoding the dataset's camera alone, in the chunks the relabeller reads."""
    (camera,) = meta.video_keys
    start = time.perf_counter()
    reader = CameraFrames(meta, "pyav", None)
    frames = sum(len(reader.frames(camera, e, lo, hi)) for e, lo, hi in episode_spans(meta, batch_size))
    return frames / (time.perf_counter() - start)


# name -> (work folder, dataset label, lerobot-iupe-collect flags); video datasets are also decoded alone
DATASETS = {
    "cartpole": (
        "cartpole-100", "CartPole state",
        ["--env.type=cartpole", "--agent=expert", "--episodes=100", "--seed=710000", "--keep_actions=true"],
    ),
    "maze5": (
        "maze5-video-200", "Maze 5×5 64×64 AV1 video (pyav)",
        ["--env.type=maze", "--env.size=5", "--agent=random", "--random_start=true", "--episodes=200", "--seed=720000"],
    ),
    "so101_camera": (
        "so101-camera-100", "SO-101 front camera 64×64 AV1 video (pyav) + state",
        ["--env.type=so101_pickplace", "--env.image_obs=true", "--env.image_size=64", "--agent=expert",
         "--episodes=100", "--seed=730000", "--keep_actions=true"],
    ),
}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS), choices=list(DATASETS))
    parser.add_argument("--batch_size", type=int, default=512)
    parser.add_argument("--work", default="outputs/measure-throughput")
    parser.add_argument("--out", default="benchmarks")
    args = parser.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.datasets:
        folder, label, collect = DATASETS[name]
        root, idm = prepare(work, folder, collect)
        meta = LeRobotDatasetMetadata("local/d", root=root)
        decode = decode_rate(meta, args.batch_size) if meta.video_keys else None
        for processes in (1, 2):
            rows.append(
                {
                    "dataset": f"{label}, {meta.total_frames} frames",
                    "processes": processes,
                    "relabel_fps": relabel_rate(idm, root, processes, args.batch_size),
                    "decode_fps": decode,
                }
            )
            print(rows[-1], flush=True)
    command = command_line()
    update(Path(args.out), "throughput", rows, command, key=("dataset", "processes"))
    print(render(Path(args.out)))


if __name__ == "__main__":
    main()
