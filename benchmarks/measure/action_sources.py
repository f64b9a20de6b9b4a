"""Every action dimension from its best source, on the generator's hand-guided arm (``VELOCITY_ARM``: six measured joint
velocities over jittered real time steps, a keyboard gripper that only the wrist camera shows, joint_4 idle in the
labelled episodes and moving in the held-out ones): for 2 and 5 labelled episodes, ``lerobot-train --policy.type=iupe
--policy.supervised=true --batch_size=64`` and otherwise default flags, then ``lerobot-iupe-relabel`` on 10 held-out
episodes with actions. Per dimension: the IDM's R², the ridge on the state window, the best difference copy, and for the
gripper a ridge on 32×24 grey thumbnails of frames t and t+5 (fitted on the labelled episodes) and the accuracy of
labels rounded to 0/1. ``--seeds`` trains each count once per seed (the spread of a row); ``--resize_shape`` sets the
IDM's working resolution (default: the policy's own).

    python benchmarks/measure/action_sources.py [--labelled 2 5] [--steps 1000] [--size 96 128] [--seeds 1000 1 2]
        [--resize_shape 72 96]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from PIL import Image

from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.data.episodes import column_array
from lerobot_iupe.data.hand_guided_arm import VELOCITY_ARM
from lerobot_iupe.policy.algorithm import r_squared
from lerobot_iupe.policy.joint_idm import REFERENCE_ALPHA, fit_ridge
from lerobot_iupe.relabel.config import CheckpointRef, RelabelConfig, RelabelDataset
from lerobot_iupe.relabel.run import relabel

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, dry_run, parse_with_folders, resolution_of, train_once  # noqa: E402

FRAMES, HELD_OUT, FPS, IDLE = 150, 10, 10, "joint_4"
TRAIN = ("--policy.type=iupe", "--policy.supervised=true", "--batch_size=64")


def recording(root: Path, episodes: int, seed: int, size: tuple[int, int], idle: tuple[str, ...]) -> Path:
    if not (root / "meta" / "info.json").exists():
        shutil.rmtree(root, ignore_errors=True)
        write_arm_recording(root, episodes, FRAMES, *size, fps=FPS, seed=seed, repo_id=f"local/{root.name}",
                            body=VELOCITY_ARM, idle=idle)  # fmt: skip
    return root


def thumbnails(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: 32×24 grey thumbnails of the wrist camera at t and t+5 (clamped into the episode), the actions and
    the episode."""
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    grey = np.stack([
        np.asarray(Image.fromarray((dataset[i]["observation.images.wrist"].permute(1, 2, 0).numpy() * 255)
                                   .astype(np.uint8)).convert("L").resize((32, 24)), np.float32).reshape(-1) / 255
        for i in range(len(dataset))
    ])  # fmt: skip
    hf = dataset.hf_dataset
    episodes = column_array(hf, "episode_index").reshape(-1)
    actions = column_array(hf, "action").reshape(len(hf), -1)
    rows = np.arange(len(hf))
    first = np.array([np.flatnonzero(episodes == e)[0] for e in episodes])
    last = np.array([np.flatnonzero(episodes == e)[-1] for e in episodes])
    later = np.clip(rows + 5, first, last)
    return np.concatenate([grey, grey[later]], axis=1), actions, episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--labelled", type=int, nargs="+", default=[2, 5], help="labelled episodes")
    parser.add_argument("--steps", type=int, default=1000, help="training steps")
    parser.add_argument("--size", type=int, nargs=2, default=[96, 128], metavar=("H", "W"), help="camera size")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1000], help="training seeds (lerobot-train's default)")
    parser.add_argument("--resize_shape", type=int, nargs=2, metavar=("H", "W"), help="the IDM's working resolution")
    args = parse_with_folders(parser, "outputs/action-sources")
    work, size = Path(args.work), tuple(args.size)
    held_out = recording(work / "held-out", HELD_OUT, 100, size, ())
    held_thumbs, held_actions, _ = thumbnails(held_out)
    rows = []
    resize = [f"--policy.resize_shape=[{args.resize_shape[0]},{args.resize_shape[1]}]"] if args.resize_shape else []
    runs = [(count, seed) for count in args.labelled for seed in args.seeds]
    for count, seed in runs:
        labelled = recording(work / f"labelled-{count}", count, 0, size, (IDLE,))
        # the first runs' folder names (seed 1000, the default resolution) are kept, so that they are reused
        name = f"{count}" + ("" if seed == 1000 else f"-seed{seed}")
        name += f"-{args.resize_shape[0]}x{args.resize_shape[1]}" if args.resize_shape else ""
        start = time.perf_counter()
        checkpoint = train_once(labelled, work / f"run-{name}", *TRAIN, f"--seed={seed}", *resize, steps=args.steps,
                                threads=2)  # fmt: skip
        train_s = time.perf_counter() - start
        report = dry_run(checkpoint, held_out)
        relabelled = work / f"relabelled-{name}"
        shutil.rmtree(relabelled, ignore_errors=True)
        shutil.copytree(held_out, relabelled)
        dataset = RelabelDataset(repo_id="local/relabelled", root=str(relabelled), video_backend="pyav")
        relabel(RelabelConfig(policy=CheckpointRef(path=str(checkpoint)), dataset=dataset, overwrite=True))
        labels = column_array(LeRobotDataset("local/relabelled", root=relabelled).hf_dataset, "action")
        labels = labels.reshape(len(labels), -1)
        thumbs, actions, episodes = thumbnails(labelled)
        weight, bias, *_ = fit_ridge(thumbs, actions[:, [6]], episodes, (REFERENCE_ALPHA,))
        thumb_pred = held_thumbs @ weight + bias
        inner = np.ones(len(labels), dtype=bool)  # the dry run scores frames with a successor; so does this
        references = report.references
        rows.append({
            "labelled": count, "seed": seed, "resolution": resolution_of(checkpoint),
            "steps": args.steps, "train_s": round(train_s, 1),
            "dimensions": VELOCITY_ARM.action_names, "source": references["source"],
            "idm": report.agreement_per_dimension, "ridge": references["ridge"],
            "difference_copy": references["difference"],
            "gripper_thumbnail_ridge": r_squared(thumb_pred[inner, 0], held_actions[inner, 6]),
            "gripper_checkpoint_thumbnail_ridge": references["thumbnails"][6],
            "gripper_thumbnail_accuracy": float(((thumb_pred[:, 0] > 0.5) == (held_actions[:, 6] > 0.5)).mean()),
            "gripper_accuracy": float(((labels[:, 6] > 0.5) == (held_actions[:, 6] > 0.5)).mean()),
        })  # fmt: skip
        print(json.dumps(rows[-1]))
    lines = [
        "# Every action dimension from its best source: the generator's hand-guided arm",
        "",
        f"`{command_line()}` — {HELD_OUT} held-out episodes of {FRAMES} frames at {FPS} fps, cameras "
        f"{size[1]}×{size[0]} (AV1); joint_4 idle in the labelled episodes. R² per dimension on the held-out "
        "frames with a successor.",
        "",
        "| labelled | seed | working resolution | dimension | source | IDM | ridge (state window) | difference copy | "
        "IDM − best simple fit |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        for j, name in enumerate(row["dimensions"]):
            simple = [row["ridge"][j], row["difference_copy"][j]]
            if name == "gripper":
                simple = [row["ridge"][j], row["gripper_thumbnail_ridge"]]
            simple = [v for v in simple if v == v]
            difference = row["difference_copy"][j]
            lines.append(
                f"| {row['labelled']} | {row['seed']} | {row['resolution']} | {name} | {row['source'][j]} | "
                f"{row['idm'][j]:.4f} | {row['ridge'][j]:.4f} | "
                f"{'–' if difference != difference else f'{difference:.4f}'} | {row['idm'][j] - max(simple):+.4f} |"
            )
        lines.append(
            f"| {row['labelled']} | {row['seed']} | {row['resolution']} | gripper accuracy | | "
            f"{row['gripper_accuracy']:.3f} | | | thumbnail ridge: "
            f"R² {row['gripper_thumbnail_ridge']:.4f}, accuracy {row['gripper_thumbnail_accuracy']:.3f}; the dry run's "
            f"(frames t, t+1, t+5): R² {row['gripper_checkpoint_thumbnail_ridge']:.4f} |"
        )
    lines += [
        "",
        f"Training: {args.steps} steps, "
        + ", ".join(f"{r['train_s']} s ({r['labelled']} labelled, seed {r['seed']})" for r in rows)
        + " on 2 threads.",
    ]
    for count in args.labelled:
        gripper = [r["idm"][-1] for r in rows if r["labelled"] == count]
        if len(gripper) > 1:  # the spread over seeds, ddof = 1
            lines.append(f"Gripper R² over {len(gripper)} seeds, {count} labelled: {np.mean(gripper):.4f} ± "
                         f"{np.std(gripper, ddof=1):.4f} (min {min(gripper):.4f}).")  # fmt: skip
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "action_sources.md").write_text("\n".join(lines) + "\n")
    (out / "action_sources.json").write_text(json.dumps(rows, indent=1))
    torch.set_num_threads(1)


if __name__ == "__main__":
    main()
