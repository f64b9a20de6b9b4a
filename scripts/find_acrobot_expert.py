"""Search the weights of the built-in Acrobot expert (a 6-16-3 tanh network) by the cross-entropy method.

The search runs on a batched numpy copy of gymnasium's Acrobot-v1 dynamics (one RK4 step of 0.2 s, "book"
equations) so that a whole population is simulated at once; the result is then checked on the real
gymnasium environment and written to ``lerobot_iupe/assets/acrobot_expert.safetensors``.

    python scripts/find_acrobot_expert.py --seed 0 --generations 40
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from safetensors.numpy import save_file

HIDDEN = 16
SHAPES = {"w1": (6, HIDDEN), "b1": (HIDDEN,), "w2": (HIDDEN, 3), "b2": (3,)}
N_PARAMS = sum(int(np.prod(s)) for s in SHAPES.values())
DT = 0.2
MAX_STEPS = 500


def unflatten(theta: np.ndarray) -> dict[str, np.ndarray]:
    """Split a (P, N_PARAMS) population into batched weight arrays."""
    out, i = {}, 0
    for name, shape in SHAPES.items():
        n = int(np.prod(shape))
        out[name] = theta[:, i : i + n].reshape(theta.shape[0], *shape)
        i += n
    return out


def derivs(s: np.ndarray, torque: np.ndarray) -> np.ndarray:
    m1 = m2 = 1.0
    l1, lc1, lc2, i1, i2, g = 1.0, 0.5, 0.5, 1.0, 1.0, 9.8
    t1, t2, dt1, dt2 = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * np.cos(t2)) + i1 + i2
    d2 = m2 * (lc2**2 + l1 * lc2 * np.cos(t2)) + i2
    phi2 = m2 * lc2 * g * np.cos(t1 + t2 - np.pi / 2.0)
    phi1 = (
        -m2 * l1 * lc2 * dt2**2 * np.sin(t2)
        - 2 * m2 * l1 * lc2 * dt2 * dt1 * np.sin(t2)
        + (m1 * lc1 + m2 * l1) * g * np.cos(t1 - np.pi / 2)
        + phi2
    )
    ddt2 = (torque + d2 / d1 * phi1 - m2 * l1 * lc2 * dt1**2 * np.sin(t2) - phi2) / (m2 * lc2**2 + i2 - d2**2 / d1)
    ddt1 = -(d2 * ddt2 + phi1) / d1
    return np.stack([dt1, dt2, ddt1, ddt2], axis=-1)


def step(s: np.ndarray, torque: np.ndarray) -> np.ndarray:
    k1 = derivs(s, torque)
    k2 = derivs(s + DT / 2 * k1, torque)
    k3 = derivs(s + DT / 2 * k2, torque)
    k4 = derivs(s + DT * k3, torque)
    ns = s + DT / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    ns[..., 0] = (ns[..., 0] + np.pi) % (2 * np.pi) - np.pi
    ns[..., 1] = (ns[..., 1] + np.pi) % (2 * np.pi) - np.pi
    ns[..., 2] = np.clip(ns[..., 2], -4 * np.pi, 4 * np.pi)
    ns[..., 3] = np.clip(ns[..., 3], -9 * np.pi, 9 * np.pi)
    return ns


def batched_returns(theta: np.ndarray, episodes: int, rng: np.random.Generator) -> np.ndarray:
    """Mean return of each of the P parameter vectors over `episodes` random starts."""
    w = unflatten(theta)
    pop = theta.shape[0]
    s = rng.uniform(-0.1, 0.1, size=(pop, episodes, 4))
    returns = np.zeros((pop, episodes))
    alive = np.ones((pop, episodes), dtype=bool)
    for _ in range(MAX_STEPS):
        obs = np.stack(
            [np.cos(s[..., 0]), np.sin(s[..., 0]), np.cos(s[..., 1]), np.sin(s[..., 1]), s[..., 2], s[..., 3]],
            axis=-1,
        )
        h = np.tanh(np.einsum("pei,pih->peh", obs, w["w1"]) + w["b1"][:, None, :])
        logits = np.einsum("peh,pha->pea", h, w["w2"]) + w["b2"][:, None, :]
        torque = logits.argmax(-1).astype(np.float64) - 1.0
        s = np.where(alive[..., None], step(s, torque), s)
        done = -np.cos(s[..., 0]) - np.cos(s[..., 1] + s[..., 0]) > 1.0
        returns -= alive & ~done
        alive &= ~done
        if not alive.any():
            break
    return returns.mean(axis=1)


def gymnasium_returns(weights: dict[str, np.ndarray], episodes: int, seed: int) -> tuple[float, float]:
    """Mean and std return of the network on the real gymnasium Acrobot-v1."""
    env = gym.make("Acrobot-v1")
    returns = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        total, done = 0.0, False
        while not done:
            h = np.tanh(obs @ weights["w1"] + weights["b1"])
            obs, reward, terminated, truncated, _ = env.step(int(np.argmax(h @ weights["w2"] + weights["b2"])))
            total += float(reward)
            done = terminated or truncated
        returns.append(total)
    return float(np.mean(returns)), float(np.std(returns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--generations", type=int, default=40)
    parser.add_argument("--population", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--elite_frac", type=float, default=0.2)
    parser.add_argument(
        "--output", type=Path, default=Path(__file__).parents[1] / "lerobot_iupe/assets/acrobot_expert.safetensors"
    )
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    mean, std = np.zeros(N_PARAMS), np.ones(N_PARAMS)
    n_elite = max(2, int(args.population * args.elite_frac))
    best, best_score = mean.copy(), -np.inf
    start = time.time()
    for gen in range(args.generations):
        theta = mean + std * rng.standard_normal((args.population, N_PARAMS))
        scores = batched_returns(theta, args.episodes, rng)
        elite = theta[np.argsort(scores)[-n_elite:]]
        mean, std = elite.mean(0), elite.std(0) + 0.02
        mean_score = batched_returns(mean[None], 128, rng)[0]
        if mean_score > best_score:
            best, best_score = mean.copy(), mean_score
        print(f"gen {gen:3d}  elite {scores.max():8.2f}  mean-policy {mean_score:8.2f}  ({time.time() - start:.0f}s)")
    weights = {k: v[0].astype(np.float32) for k, v in unflatten(best[None]).items()}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    save_file(weights, str(args.output))
    mean_return, std_return = gymnasium_returns(weights, episodes=100, seed=10_000)
    print(f"saved {args.output}: gymnasium Acrobot-v1 return {mean_return:.2f} ± {std_return:.2f} over 100 episodes")


if __name__ == "__main__":
    main()
