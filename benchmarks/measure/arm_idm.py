"""The linear-first IDM against the simplest fits, on the generator's arms (``lerobot_iupe.data.arm_recording``): for
each body (an SO-101; one whose wrist_roll is offset and barely follows; an SO-101 leader driving another 7-value
follower; a humanoid's two arms and hands, its left arm idle in the labelled episodes), transport delay and number of
labelled episodes, ``lerobot-train --policy.type=iupe --policy.supervised=true`` with
default flags on the labelled episodes, then ``lerobot-iupe-relabel --dry_run=true`` on 10 held-out episodes with
actions, which reports per joint the IDM's R², the plain ridge regression on the same window and training data, and
the best copy a_t ≈ s_{t+k}. ``--variant plain`` trains the IDM the paper's envs use (``joint_state_columns=[]``).

The recordings carry no camera (``--no_cameras``): the arm IDM reads observation.state alone, and LeRobot's loader
would decode every camera frame of every batch for nothing.

    python benchmarks/measure/arm_idm.py [--bodies so101 …] [--delays 2 4 6] [--labelled 2 10] [--steps 3000]
        [--variant joint|plain]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.arm_recording import HUMANOID_LEFT_ARM, ArmDynamics
from lerobot_iupe.data.arm_writer import BODIES, write_arm_recording
from lerobot_iupe.data.episodes import column_array
from lerobot_iupe.data.readers import window_indices
from lerobot_iupe.policy.action_sources import max_lag
from lerobot_iupe.relabel.references import per_dimension_r2

sys.path.insert(0, str(Path(__file__).parent))
from steps import dry_run, train_once  # noqa: E402

FRAMES = 300  # 10 s at 30 fps, as the real recording's episodes (373 frames on average)
HELD_OUT = 10


def recording(root: Path, episodes: int, seed: int, delay: int, body: str = "so101", labelled: bool = False) -> Path:
    """The humanoid's labelled episodes keep its left arm idle; its held-out ones move it."""
    idle = HUMANOID_LEFT_ARM if body == "humanoid" and labelled else ()
    if not (root / "meta" / "info.json").exists():
        write_arm_recording(root, episodes, FRAMES, seed=seed, repo_id=f"local/{root.name}",
                            dynamics=ArmDynamics(delay=delay), cameras=False, body=BODIES[body], idle=idle)  # fmt: skip
    return root


def joint_arrays(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A recording's states, actions and episode index per frame."""
    hf = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav").hf_dataset
    episodes = column_array(hf, "episode_index").reshape(-1)
    states = column_array(hf, "observation.state").reshape(len(hf), -1).astype(np.float32)
    return states, column_array(hf, "action").reshape(len(hf), -1).astype(np.float32), episodes


def mlp_r2(train_root: Path, held_out: Path, fps: int = 30, steps: int = 3000) -> list[float]:
    """The simplest network: a plain 2×256 MLP (MSE, Adam 1e-3, batch 64, seeded) from the standardised window of every
    state column, t−1 … t+0.35 s (the reference ridge's), to the standardised a_t, trained on the labelled recording;
    R² per action dimension on the held-out frames with a successor, as the dry run scores the IDM."""
    offsets = list(range(-1, max_lag(fps) + 1))

    def windows(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        states, actions, episodes = joint_arrays(root)
        first, last = np.searchsorted(episodes, episodes, "left"), np.searchsorted(episodes, episodes, "right") - 1
        rows = np.arange(len(states))
        flat = states[window_indices(rows, offsets, first, last)].reshape(len(states), -1)
        return flat, actions, rows < last

    x, y, inner = windows(train_root)
    x, y = x[inner], y[inner]
    hx, hy, held_inner = windows(held_out)
    mean, std, centre, spread = x.mean(0), x.std(0) + 1e-6, y.mean(0), y.std(0) + 1e-6
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
        torch.nn.Linear(256, y.shape[1]),
    )  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), 1e-3)
    inputs, targets = torch.as_tensor((x - mean) / std), torch.as_tensor((y - centre) / spread)
    generator = torch.Generator().manual_seed(0)
    for _ in range(steps):
        batch = torch.randint(len(inputs), (64,), generator=generator)
        loss = ((net(inputs[batch]) - targets[batch]) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = net(torch.as_tensor((hx[held_inner] - mean) / std)).numpy() * spread + centre
    return per_dimension_r2(predicted, hy[held_inner])


def train(root: Path, out: Path, steps: int, variant: str) -> Path:
    extra = ["--policy.joint_state_columns=[]"] if variant == "plain" else []
    flags = ["--policy.type=iupe", "--policy.supervised=true", "--batch_size=64", "--log_freq=1000", *extra]
    return train_once(root, out, *flags, steps=steps, threads=None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("outputs/measure-arm-idm"))
    parser.add_argument("--bodies", nargs="+", choices=sorted(BODIES), default=["so101"])
    parser.add_argument("--delays", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--labelled", type=int, nargs="+", default=[2, 10])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--variant", choices=["joint", "plain"], default="joint")
    args = parser.parse_args()
    rows = []
    for body, delay in ((b, d) for b in args.bodies for d in args.delays):
        tag = f"d{delay}" if body == "so101" else f"{body}-d{delay}"  # so101's folders keep their earlier names
        held_out = recording(args.work / f"held-out-{tag}", HELD_OUT, 1000, delay, body)
        for labelled in args.labelled:
            train_root = recording(args.work / f"train-{tag}-n{labelled}", labelled, 0, delay, body, labelled=True)
            checkpoint = train(
                train_root, args.work / f"run-{tag}-n{labelled}-{args.variant}", args.steps, args.variant
            )
            report = dry_run(checkpoint, held_out)
            config = json.loads((checkpoint / "config.json").read_text())
            refs = report.references or {}
            rows.append({"body": body, "delay": delay, "labelled": labelled, "variant": args.variant,
                         "lag": config["idm_lag"], "lags": config.get("idm_joint_lags"),
                         "window": config["idm_context"], "joints": report.action_names,
                         "idm": report.agreement_per_dimension, "mlp": mlp_r2(train_root, held_out),
                         **refs})  # fmt: skip
            print(report.summary(), flush=True)
    (args.work / f"results-{args.variant}.json").write_text(json.dumps(rows, indent=1))
    print("\n| body | delay | labelled | joint | lag | IDM | ridge | best copy (k) | IDM − best simple fit |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in rows:
        for n, name in enumerate(row["joints"]):
            ridge = row.get("ridge", [float("nan")] * len(row["joints"]))[n]
            copy, copy_lag = (row["copy"][n], row["copy_lag"][n]) if "copy" in row else (float("nan"), -1)
            best = max(ridge, copy) if copy_lag >= 0 else ridge
            copied = f"{copy:.4f} ({copy_lag})" if copy_lag >= 0 else "–"
            lag = row["lags"][n] if row.get("lags") else row["lag"]
            print(
                f"| {row.get('body', 'so101')} | {row['delay']} | {row['labelled']} | {name} | {lag} "
                f"| {row['idm'][n]:.4f} | {ridge:.4f} | {copied} | {row['idm'][n] - best:+.4f} |"
            )
    print("\n| body | delay | labelled | mean IDM | mean ridge | mean plain MLP | worst joint: IDM − best simple fit |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        gaps = [
            idm - (max(ridge, copy) if lag >= 0 else ridge)
            for idm, ridge, copy, lag in zip(row["idm"], row["ridge"], row["copy"], row["copy_lag"], strict=True)
        ]
        mean = lambda values: sum(values) / len(values)  # noqa: E731
        print(
            f"| {row.get('body', 'so101')} | {row['delay']} | {row['labelled']} | {mean(row['idm']):.4f} "
            f"| {mean(row['ridge']):.4f} | {mean(row['mlp']):.4f} | {min(gaps):+.4f} |"
        )


if __name__ == "__main__":
    main()
