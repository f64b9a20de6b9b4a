"""Write an SO-101-shaped recording with LeRobot's own writer: two cameras (640×480 by default) that show a six-joint
arm, six joint positions, the leader's absolute joint targets as actions, 30 fps (``lerobot_iupe.data.arm_recording``).
Data to try relabelling and camera training on without a robot; the tests and ``measure_cameras.py`` use it.

    python scripts/make_arm_recording.py --root data/arm --episodes 40 [--frames 250] [--state_only]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lerobot_iupe.data.arm_recording import write_arm_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", type=Path, required=True, help="where to write the dataset (must not exist)")
    parser.add_argument("--repo_id", default="local/arm-recording", help="the dataset's repo id")
    parser.add_argument("--episodes", type=int, default=10, help="episodes to record")
    parser.add_argument("--frames", type=int, default=250, help="frames per episode")
    parser.add_argument("--height", type=int, default=480, help="camera height in pixels")
    parser.add_argument("--width", type=int, default=640, help="camera width in pixels")
    parser.add_argument("--seed", type=int, default=0, help="episode i is drawn from seed + i")
    parser.add_argument("--vcodec", default="libsvtav1", help="video codec (LeRobot's default AV1, or h264)")
    parser.add_argument("--state_only", action="store_true", help="leave the actions out (a state-only recording)")
    args = parser.parse_args()
    if args.root.exists():
        parser.error(f"--root={args.root} already exists; choose a new folder")
    dataset = write_arm_recording(
        args.root, args.episodes, args.frames, args.height, args.width, seed=args.seed, repo_id=args.repo_id,
        vcodec=args.vcodec, with_actions=not args.state_only, progress=True,
    )  # fmt: skip
    print(f"wrote {dataset.meta.total_frames} frames in {dataset.meta.total_episodes} episodes to {args.root}")


if __name__ == "__main__":
    main()
