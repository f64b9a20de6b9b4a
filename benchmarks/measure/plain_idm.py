"""The simplest loop beside the package's camera IDM: a plain torch MLP on the joint state alone, (s_t, s_{t+1})
→ a_t, trained on the same 2,000-frame SO-101-shaped recording as ``cameras.py`` (same steps and batch as
its IDM) and scored by R² per joint on the same 10 held-out episodes.

    python benchmarks/measure/plain_idm.py [--work outputs/measure-cameras] [--steps 1500] [--batch_size 8]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.episodes import column_array


def pairs(root: Path) -> tuple[np.ndarray, np.ndarray]:
    hf = LeRobotDataset("local/x", root=root, video_backend="pyav").hf_dataset
    state = column_array(hf, "observation.state").astype(np.float32)
    action = column_array(hf, "action").astype(np.float32)
    episode = column_array(hf, "episode_index")
    keep = np.flatnonzero(episode[:-1] == episode[1:])
    return np.concatenate([state[keep], state[keep + 1] - state[keep]], axis=1), action[keep]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("outputs/measure-cameras"))
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--batch_size", type=int, default=8)
    args = parser.parse_args()
    torch.manual_seed(0)
    x, y = pairs(args.work / "arm-2000")
    hx, hy = pairs(args.work / "arm-held-out")
    mx, sx, my, sy = x.mean(0), x.std(0) + 1e-6, y.mean(0), y.std(0) + 1e-6
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                              torch.nn.ReLU(), torch.nn.Linear(256, y.shape[1]))  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    tx, ty = torch.as_tensor((x - mx) / sx), torch.as_tensor((y - my) / sy)
    rng = np.random.default_rng(0)
    for _ in range(args.steps):
        idx = torch.as_tensor(rng.integers(len(tx), size=args.batch_size))
        loss = torch.nn.functional.mse_loss(net(tx[idx]), ty[idx])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        predicted = net(torch.as_tensor((hx - mx) / sx)).numpy() * sy + my
    r2 = 1 - ((predicted - hy) ** 2).mean(0) / hy.var(0)
    print("held-out R² per joint:", ", ".join(f"{v:.4f}" for v in r2), f"(min {r2.min():.4f})")


if __name__ == "__main__":
    main()
