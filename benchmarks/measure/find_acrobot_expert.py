"""Search the weights of the built-in Acrobot expert (a 6-16-3 tanh network) by the cross-entropy method.

The search runs on a batched numpy copy of gymnasium's Acrobot-v1 dynamics (one RK4 step of 0.2 s, "book"
equations) so that a whole population is simulated at once; the result is then checked on the real
gymnasium environment and written to ``lerobot_iupe/assets/acrobot_expert.safetensors``.

    python benchmarks/measure/find_acrobot_expert.py --seed 0 --generations 40
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from safetensors.numpy import save_file

from lerobot_iupe.envs.acrobot_dynamics import observation, step, tip_height

HIDDEN = 16
SHAPES = {"w1": (6, HIDDEN), "b1": (HIDDEN,), "w2": (HIDDEN, 3), "b2": (3,)}
N_PARAMS = sum(int(np.prod(s)) for s in SHAPES.values())
MAX_STEPS = 500


def unflatten(theta: np.ndarray) -> dict[str, np.ndarray]:
    """Split a (P, N_PARAMS) population into batched weight arrays."""
    out, i = {}, 0
    for name, shape in SHAPES.items():
        n = int(np.prod(shape))
        out[name] = theta[:, i : i + n].reshape(theta.shape[0], *shape)
        i += n
    return out


def batched_returns(theta: np.ndarray, episodes: int, rng: np.random.Generator) -> np.ndarray:
    """Mean return of each of the P parameter vectors over `episodes` random starts."""
    w = unflatten(theta)
    pop = theta.shape[0]
    s = rng.uniform(-0.1, 0.1, size=(pop, episodes, 4))
    returns = np.zeros((pop, episodes))
    alive = np.ones((pop, episodes), dtype=bool)
    for _ in range(MAX_STEPS):
        obs = observation(s)
        h = np.tanh(np.einsum("pei,pih->peh", obs, w["w1"]) + w["b1"][:, None, :])
        logits = np.einsum("peh,pha->pea", h, w["w2"]) + w["b2"][:, None, :]
        torque = logits.argmax(-1).astype(np.float64) - 1.0
        s = np.where(alive[..., None], step(s, torque), s)
        done = tip_height(s) > 1.0
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
        "--output", type=Path, default=Path(__file__).parents[2] / "lerobot_iupe/assets/acrobot_expert.safetensors"
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
