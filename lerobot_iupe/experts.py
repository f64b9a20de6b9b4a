"""Built-in experts and the uniform-random agent, and their reference returns.

Every agent is a callable ``agent(env, observation) -> action`` (an int id, or a float32 array for a ``Box``
action) acting on one environment made from the package's env configs (``env`` is the ``gym.make`` result, so an
agent may look at the simulator when it needs to, as the maze's shortest-path expert does).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from importlib import resources
from pathlib import Path

import gymnasium as gym
import numpy as np
from safetensors.numpy import load_file
from tqdm.auto import tqdm

from lerobot_iupe.envs.configs import IUPEEnvConfig
from lerobot_iupe.envs.rollout import agent_act, run_episodes

Agent = Callable[[gym.Env, dict], int | np.ndarray]
AGENTS = ("expert", "random", "play")
CARTPOLE_GAINS = np.array([0.1, 0.5, 10.0, 1.0])


def cartpole_expert(env: gym.Env, observation: dict) -> int:
    """Linear state feedback: push towards the side the pole is falling to."""
    return int(CARTPOLE_GAINS @ observation["agent_pos"] > 0)


class MountainCarExpert:
    """Value iteration on a grid of (position, velocity) with bilinear interpolation; greedy one-step lookahead.

    Gymnasium's dynamics are deterministic and cheap, so planning is exact up to the grid (≈1 s to solve)."""

    LOW = np.array([-1.2, -0.07])
    HIGH = np.array([0.6, 0.07])

    def __init__(self, grid: int = 201, iterations: int = 1000, tolerance: float = 1e-6):
        self.grid = grid
        axes = [np.linspace(lo, hi, grid) for lo, hi in zip(self.LOW, self.HIGH, strict=True)]
        states = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 2)
        transitions = [self._successor(states, a) for a in range(3)]
        values = np.zeros(grid * grid)
        for _ in range(iterations):
            q = np.stack([-1.0 + np.where(done, 0.0, self._interpolate(values, nxt)) for nxt, done in transitions])
            new_values = q.max(axis=0)
            converged = np.abs(new_values - values).max() < tolerance
            values = new_values
            if converged:
                break
        self.values = values

    @staticmethod
    def _successor(states: np.ndarray, action: int) -> tuple[np.ndarray, np.ndarray]:
        position, velocity = states[..., 0], states[..., 1]
        velocity = np.clip(velocity + (action - 1) * 0.001 - 0.0025 * np.cos(3 * position), -0.07, 0.07)
        position = np.clip(position + velocity, -1.2, 0.6)
        velocity = np.where((position <= -1.2) & (velocity < 0), 0.0, velocity)
        done = (position >= 0.5) & (velocity >= 0)
        return np.stack([position, velocity], axis=-1), done

    def _interpolate(self, values: np.ndarray, states: np.ndarray) -> np.ndarray:
        scaled = (states - self.LOW) / (self.HIGH - self.LOW) * (self.grid - 1)
        lower = np.clip(np.floor(scaled).astype(np.int64), 0, self.grid - 2)
        frac = np.clip(scaled - lower, 0.0, 1.0)
        grid = values.reshape(self.grid, self.grid)
        i, j, fi, fj = lower[..., 0], lower[..., 1], frac[..., 0], frac[..., 1]
        return (
            grid[i, j] * (1 - fi) * (1 - fj)
            + grid[i + 1, j] * fi * (1 - fj)
            + grid[i, j + 1] * (1 - fi) * fj
            + grid[i + 1, j + 1] * fi * fj
        )

    def __call__(self, env: gym.Env, observation: dict) -> int:
        state = np.asarray(observation["agent_pos"], dtype=np.float64)
        scores = []
        for action in range(3):
            nxt, done = self._successor(state, action)
            scores.append(-1.0 + (0.0 if done else float(self._interpolate(self.values, nxt))))
        return int(np.argmax(scores))


class AcrobotExpert:
    """A 6-16-3 tanh network over the observation, found by ``benchmarks/measure/find_acrobot_expert.py``."""

    def __init__(self, weights: dict[str, np.ndarray]):
        self.weights = weights

    @classmethod
    def from_file(cls, path: str | Path | None = None) -> AcrobotExpert:
        if path is None:
            path = resources.files("lerobot_iupe") / "assets" / "acrobot_expert.safetensors"
        return cls(load_file(str(path)))

    def __call__(self, env: gym.Env, observation: dict) -> int:
        w = self.weights
        hidden = np.tanh(observation["agent_pos"] @ w["w1"] + w["b1"])
        return int(np.argmax(hidden @ w["w2"] + w["b2"]))


def maze_expert(env: gym.Env, observation: dict) -> int:
    """Shortest path by breadth-first search on the true layout."""
    return env.unwrapped.expert_action()


def env_expert(env: gym.Env, observation: dict) -> np.ndarray:
    """The expert an env carries itself (``expert_action``): LunarLander's heuristic, SO-101's and Meta-World's
    scripted controllers."""
    return env.get_wrapper_attr("expert_action")()


def random_agent(env: gym.Env, observation: dict) -> int | np.ndarray:
    """Uniform over the action space (ids, or a ``Box`` between its bounds), from the env's own seeded generator."""
    space, rng = env.action_space, env.unwrapped.np_random
    if isinstance(space, gym.spaces.Discrete):
        return int(rng.integers(space.n))
    return rng.uniform(space.low, space.high).astype(np.float32)


def env_play(env: gym.Env, observation: dict) -> np.ndarray:
    """The goal-agnostic play agent an env carries itself (``play_action``): SO-101's, Meta-World's."""
    return env.get_wrapper_attr("play_action")()


PLAY_AGENTS = {"so101_pickplace": env_play, "metaworld_state": env_play}


@cache
def _mountaincar_expert() -> MountainCarExpert:
    return MountainCarExpert()


def make_agent(env_type: str, agent: str) -> Agent:
    """The built-in agent ``agent`` (``expert``, ``random`` or ``play``) for an env type of this package."""
    if agent not in AGENTS:
        raise ValueError(f"--agent must be one of {list(AGENTS)}, got {agent!r}")
    if agent == "random":
        return random_agent
    if agent == "play":
        if env_type not in PLAY_AGENTS:
            raise ValueError(
                f"--agent=play: env type {env_type!r} has no play agent (envs with one: {sorted(PLAY_AGENTS)}); "
                "use --agent=random"
            )
        return PLAY_AGENTS[env_type]
    experts = {
        "cartpole": lambda: cartpole_expert,
        "mountaincar": _mountaincar_expert,
        "acrobot": AcrobotExpert.from_file,
        "maze": lambda: maze_expert,
        "lunarlander": lambda: env_expert,
        "so101_pickplace": lambda: env_expert,
        "metaworld_state": lambda: env_expert,
    }
    if env_type not in experts:
        raise ValueError(f"no built-in expert for env type {env_type!r}; expected one of {sorted(experts)}")
    return experts[env_type]()


def agent_episodes(
    env_cfg: IUPEEnvConfig, agent: str, episodes: int = 100, seed: int = 100_000
) -> tuple[np.ndarray, np.ndarray]:
    """Returns and successes of ``episodes`` seeded episodes (seeds ``seed, seed+1, …``) of a built-in agent."""
    env = env_cfg.make()
    act = agent_act([env], make_agent(env_cfg.type, agent))
    played = [
        run_episodes([env], act, [seed + i])[0]
        for i in tqdm(range(episodes), desc=f"{env_cfg.type} {agent}", leave=False)
    ]
    env.close()
    return np.asarray([e.total_reward for e in played]), np.asarray([e.success for e in played])


def reference_returns(env_cfg: IUPEEnvConfig, agent: str, episodes: int = 100, seed: int = 100_000) -> np.ndarray:
    """Returns of ``episodes`` seeded episodes (seeds ``seed, seed+1, …``) of a built-in agent."""
    return agent_episodes(env_cfg, agent, episodes, seed)[0]
