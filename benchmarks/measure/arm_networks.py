"""Why the arm IDM's network is one small MLP per joint: on the generator's follower (numpy episodes, no dataset),
a ridge regression on the residual a_t − s_{t+lag} over the window t−1 … t+lag+2, then an MLP trained 3,000 steps
(batch 64, Adam 1e-3) on what it leaves: over every joint's window at once, or one per joint over its own window;
beside them the simplest network, a plain MLP from the same window to a_t with no ridge.
R² per joint on 10 held-out episodes. A quick look at extrapolation, not the package's model
(benchmarks/measure/arm_idm.py measures that).

    python benchmarks/measure/arm_networks.py [--delays 2 6] [--labelled 2 10]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from lerobot_iupe.data.arm_recording import ArmDynamics, teleoperated_episode
from lerobot_iupe.policy.action_sources import best_copy_lag


def episodes(count: int, seed: int, dynamics: ArmDynamics) -> list[tuple[np.ndarray, np.ndarray]]:
    return [teleoperated_episode(300, np.random.default_rng(seed + i), dynamics) for i in range(count)]


def windows(data, offsets: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Windows (N, F, 6) and actions (N, 6) of every frame with a successor."""
    xs, ys = [], []
    for states, actions in data:
        index = np.clip(np.arange(len(states))[:, None] + np.asarray(offsets)[None], 0, len(states) - 1)
        xs.append(states[index][:-1])
        ys.append(actions[:-1])
    return np.concatenate(xs), np.concatenate(ys)


def r2(predicted: np.ndarray, true: np.ndarray) -> np.ndarray:
    return 1 - ((predicted - true) ** 2).sum(0) / ((true - true.mean(0)) ** 2).sum(0)


def network(inputs: int, joints: int, per_joint: bool) -> torch.nn.Module:
    if per_joint:  # grouped 1×1 convolutions: one MLP per joint over that joint's own window
        layers = [torch.nn.Conv1d(inputs, joints * 64, 1, groups=joints), torch.nn.ReLU(),
                  torch.nn.Conv1d(joints * 64, joints * 64, 1, groups=joints), torch.nn.ReLU(),
                  torch.nn.Conv1d(joints * 64, joints, 1, groups=joints)]  # fmt: skip
    else:
        layers = [torch.nn.Conv1d(inputs, 64, 1), torch.nn.ReLU(), torch.nn.Conv1d(64, 64, 1), torch.nn.ReLU(),
                  torch.nn.Conv1d(64, joints, 1)]  # fmt: skip
    torch.nn.init.zeros_(layers[-1].weight)
    torch.nn.init.zeros_(layers[-1].bias)
    return torch.nn.Sequential(*layers)


def measure(delay: int, labelled: int) -> None:
    dynamics = ArmDynamics(delay=delay)
    train, held_out = episodes(labelled, 0, dynamics), episodes(10, 1000, dynamics)
    states = np.concatenate([s for s, _ in train])
    actions = np.concatenate([a for _, a in train])
    lag = best_copy_lag(states, actions, np.repeat(np.arange(labelled), 300), list(range(6)))
    offsets = list(range(-1, lag + 3))
    x, y = windows(train, offsets)
    hx, hy = windows(held_out, offsets)
    copy, held_copy = x[:, offsets.index(lag)], hx[:, offsets.index(lag)]
    flat, held_flat = x.reshape(len(x), -1), hx.reshape(len(hx), -1)
    mean, std = flat.mean(0), flat.std(0) + 1e-6
    z, hz = (flat - mean) / std, (held_flat - mean) / std
    residual = y - copy
    coef = np.linalg.solve(z.T @ z + np.eye(z.shape[1]), z.T @ (residual - residual.mean(0)))
    prior, held_prior = copy + z @ coef + residual.mean(0), held_copy + hz @ coef + residual.mean(0)
    print(f"delay {delay}, {labelled} labelled episodes, lag {lag}")
    print(f"  {'ridge on the residual':<28}", r2(held_prior, hy).round(4))
    scale = y.std(0) + 1e-6
    joint_major = lambda v: torch.as_tensor(  # noqa: E731
        v.reshape(len(v), len(offsets), 6).transpose(0, 2, 1).reshape(len(v), -1, 1), dtype=torch.float32
    )
    names = {(False, False): "plain MLP, no ridge", (False, True): "+ one MLP over every joint",
             (True, True): "+ one MLP per joint"}  # fmt: skip
    for per_joint, on_ridge in names:
        base, held_base = (prior, held_prior) if on_ridge else (y.mean(0), y.mean(0))
        torch.manual_seed(0)
        net = network(6 * len(offsets), 6, per_joint)
        optimizer = torch.optim.Adam(net.parameters(), 1e-3)
        inputs, target = joint_major(z), torch.as_tensor((y - base) / scale, dtype=torch.float32)
        generator = torch.Generator().manual_seed(0)
        for _ in range(3000):
            batch = torch.randint(len(inputs), (64,), generator=generator)
            loss = ((net(inputs[batch]).squeeze(-1) - target[batch]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            predicted = held_base + net(joint_major(hz)).squeeze(-1).numpy() * scale
        print(f"  {names[per_joint, on_ridge]:<28}", r2(predicted, hy).round(4))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--delays", type=int, nargs="+", default=[2, 6])
    parser.add_argument("--labelled", type=int, nargs="+", default=[2, 10])
    args = parser.parse_args()
    torch.set_num_threads(1)
    for delay in args.delays:
        for labelled in args.labelled:
            measure(delay, labelled)


if __name__ == "__main__":
    main()
