"""The working resolution for 640×480 cameras (``--policy.resize_shape``), chosen by measurement: on the 2,000-frame
SO-101-shaped recording of ``cameras.py`` (run that first), a supervised IDM per resolution trained with
otherwise default flags; its R² per joint on the 10 held-out episodes, training steps/s and relabelling frames/s
(torchcodec, the decoder LeRobot picks here). With ``--cameras_only`` the IDM reads the two cameras alone: the
arm's state tells its own motion, so only then does the picture decide the labels.

    python benchmarks/measure/resolution.py [--shapes 48x64 96x128 144x192] [--steps 500] [--cameras_only]

Writes the "resolution" section of benchmarks/relabel.json and renders benchmarks/relabel.md.
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from cameras import CHECKPOINT, measured  # noqa: E402
from relabel_report import update  # noqa: E402
from steps import BIN, command_line, printed_r2  # noqa: E402

from lerobot_iupe.data.arm_recording import CAMERAS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shapes", nargs="+", default=["48x64", "96x128", "144x192"], help="HxW working resolutions")
    parser.add_argument("--steps", type=int, default=500, help="training steps of each IDM")
    parser.add_argument(
        "--cameras_only", action="store_true", help="the IDM reads the two cameras alone (not observation.state)"
    )
    parser.add_argument("--work", type=Path, default=Path("outputs/measure-cameras"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    args = parser.parse_args()
    command = command_line()
    root, held_out = args.work / "arm-2000", args.work / "arm-held-out"
    if not (root / "meta" / "info.json").exists():
        raise SystemExit(f"{root} is missing: run python benchmarks/measure/cameras.py --frames 2000 first")
    env = {"LEROBOT_IUPE_CACHE": str(args.work / "frame-cache")}
    rows = []
    for shape in args.shapes:
        h, w = (int(v) for v in shape.split("x"))
        reads = "cameras" if args.cameras_only else "cameras and state"
        out = args.work / f"arm-2000-idm-{args.steps}-{h}x{w}{'-cameras' if args.cameras_only else ''}"
        # The camera IDM (cameras alone, or with the state), not the arm IDM of the joint states.
        only = [f"--policy.idm_observation_keys=[{','.join(CAMERAS)}]"] if args.cameras_only else []
        only = only or ["--policy.joint_state_columns=[]"]
        train = measured(
            str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
            f"--policy.resize_shape=[{h},{w}]", f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}",
            f"--output_dir={out}", f"--steps={args.steps}", f"--save_freq={args.steps}", "--log_freq=50",
            "--policy.device=cpu", "--wandb.enable=false", *only, env=env,
        )  # fmt: skip
        updates = [float(u) + float(d) for u, d in re.findall(r"updt_s:([\d.]+) data_s:([\d.]+)", train["output"])]
        scored = measured(
            str(BIN / "lerobot-iupe-relabel"), f"--policy.path={out / CHECKPOINT}", "--dataset.repo_id=local/held",
            f"--dataset.root={held_out}", "--dry_run=true", env=env,
        )  # fmt: skip
        r2 = list(printed_r2(scored["output"]).values())
        relabel = measured(
            str(BIN / "lerobot-iupe-relabel"), f"--policy.path={out / CHECKPOINT}", "--dataset.repo_id=local/x",
            f"--dataset.root={root}", "--dry_run=true", "--dataset.video_backend=torchcodec", env=env,
        )  # fmt: skip
        rows.append({
            "shape": [h, w], "steps": args.steps, "idm_reads": reads, "held_out_r2": r2,
            "train_steps_per_s": 1.0 / np.mean(updates[len(updates) // 2 :]),
            "relabel_frames_per_s": float(re.search(r"\((\d+) frames/s\)", relabel["output"]).group(1)),
        })  # fmt: skip
        print(rows[-1], flush=True)
    update(args.out, "resolution", rows, command, key=("shape", "steps", "idm_reads"))


if __name__ == "__main__":
    main()
