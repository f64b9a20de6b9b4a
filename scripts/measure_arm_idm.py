"""The arm IDM against the simplest fits, on the generator's follower (``lerobot_iupe.data.arm_recording``): for each
transport delay and number of labelled episodes, ``lerobot-train --policy.type=iupe --policy.supervised=true`` with
default flags on the labelled episodes, then ``lerobot-iupe-relabel --dry_run=true`` on 10 held-out episodes with
actions, which reports per joint the IDM's R², the plain ridge regression on the same window and training data, and
the best copy a_t ≈ s_{t+k}. ``--variant plain`` trains the IDM the paper's envs use (``joint_state_columns=[]``).

The recordings carry no camera (``--no_cameras``): the arm IDM reads observation.state alone, and LeRobot's loader
would decode every camera frame of every batch for nothing.

    python scripts/measure_arm_idm.py [--delays 2 4 6] [--labelled 2 10] [--steps 3000] [--variant joint|plain]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from lerobot_iupe.data.arm_recording import ArmDynamics, write_arm_recording
from lerobot_iupe.relabel.config import CheckpointRef, RelabelConfig, RelabelDataset
from lerobot_iupe.relabel.run import relabel

BIN = Path(sys.executable).parent
FRAMES = 300  # 10 s at 30 fps, as the real recording's episodes (373 frames on average)
HELD_OUT = 10


def recording(root: Path, episodes: int, seed: int, delay: int) -> Path:
    if not (root / "meta" / "info.json").exists():
        write_arm_recording(root, episodes, FRAMES, seed=seed, repo_id=f"local/{root.name}",
                            dynamics=ArmDynamics(delay=delay), cameras=False)  # fmt: skip
    return root


def train(root: Path, out: Path, steps: int, variant: str) -> Path:
    checkpoint = out / "checkpoints" / "last" / "pretrained_model"
    if checkpoint.exists():
        return checkpoint
    extra = ["--policy.joint_state_columns=[]"] if variant == "plain" else []
    command = [
        str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
        f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", f"--steps={steps}", "--batch_size=64",
        f"--save_freq={steps}", "--num_workers=0",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", f"--output_dir={out}",
        "--log_freq=1000", *extra,
    ]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True)
    (out.parent / f"{out.name}.log").write_text(result.stdout + result.stderr)
    if result.returncode:
        raise SystemExit(f"training failed ({out.parent / f'{out.name}.log'}):\n{result.stderr[-2000:]}")
    return checkpoint


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("outputs/measure-arm-idm"))
    parser.add_argument("--delays", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--labelled", type=int, nargs="+", default=[2, 10])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--variant", choices=["joint", "plain"], default="joint")
    args = parser.parse_args()
    rows = []
    for delay in args.delays:
        held_out = recording(args.work / f"held-out-d{delay}", HELD_OUT, 1000, delay)
        for labelled in args.labelled:
            train_root = recording(args.work / f"train-d{delay}-n{labelled}", labelled, 0, delay)
            checkpoint = train(
                train_root, args.work / f"run-d{delay}-n{labelled}-{args.variant}", args.steps, args.variant
            )
            report = relabel(RelabelConfig(
                policy=CheckpointRef(path=str(checkpoint)),
                dataset=RelabelDataset(repo_id=f"local/{held_out.name}", root=str(held_out), video_backend="pyav"),
                dry_run=True,
            ))  # fmt: skip
            config = json.loads((checkpoint / "config.json").read_text())
            refs = report.references or {}
            rows.append({"delay": delay, "labelled": labelled, "variant": args.variant, "lag": config["idm_lag"],
                         "window": config["idm_context"], "joints": report.action_names,
                         "idm": report.agreement_per_dimension, **refs})  # fmt: skip
            print(report.summary(), flush=True)
    (args.work / f"results-{args.variant}.json").write_text(json.dumps(rows, indent=1))
    print("\n| delay | labelled | lag | joint | IDM | ridge | best copy (k) | IDM − ridge |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        for n, name in enumerate(row["joints"]):
            ridge = row.get("ridge", [float("nan")] * 6)[n]
            copy = f"{row['copy'][n]:.4f} ({row['copy_lag'][n]})" if "copy" in row else "–"
            print(
                f"| {row['delay']} | {row['labelled']} | {row['lag']} | {name} | {row['idm'][n]:.4f} | {ridge:.4f} "
                f"| {copy} | {row['idm'][n] - ridge:+.4f} |"
            )


if __name__ == "__main__":
    main()
