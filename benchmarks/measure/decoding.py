"""Decode rate of the package's video frames with PyAV and with torchcodec (which needs a system FFmpeg).

    python benchmarks/measure/decoding.py [--episodes 50] [--image_size 64] [--repeats 3]
Collects a Maze 5×5 expert dataset stored as MP4 (outputs/measure-decoding/, once), then decodes every frame in
the spans the relabeller and the frame cache read (``data.video.CameraFrames``), alternating the two backends.
"""

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDatasetMetadata

from lerobot_iupe.data.episodes import episode_spans
from lerobot_iupe.data.video import CameraFrames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--image_size", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch_size", type=int, default=512)
    args = parser.parse_args()
    root = Path(f"outputs/measure-decoding/maze5-{args.image_size}px-{args.episodes}")
    if not root.exists():
        subprocess.run(
            [str(Path(sys.executable).parent / "lerobot-iupe-collect"), "--env.type=maze", "--env.size=5",
             f"--env.image_size={args.image_size}", "--agent=expert", f"--episodes={args.episodes}",
             f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}"],
            check=True, capture_output=True,
        )  # fmt: skip
    meta = LeRobotDatasetMetadata(f"local/{root.name}", root=root)
    rates = {"pyav": [], "torchcodec": []}
    for _ in range(args.repeats):
        for backend in rates:
            start = time.perf_counter()
            reader = CameraFrames(meta, backend, None)
            spans = episode_spans(meta, args.batch_size)
            frames = sum(len(reader.frames("observation.image", e, lo, hi)) for e, lo, hi in spans)
            rates[backend].append(frames / (time.perf_counter() - start))
    print(f"{meta.total_frames} frames of {args.image_size}×{args.image_size} video, {args.repeats} repeats:")
    for backend, values in rates.items():
        print(f"  {backend}: {np.mean(values):,.0f} ± {np.std(values):,.0f} frames/s")


if __name__ == "__main__":
    main()
