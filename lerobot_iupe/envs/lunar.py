"""Gymnasium's LunarLanderContinuous-v3, shaped for LeRobot (``--env.type=lunarlander``).

The whole 8-D state (position, velocity, angle, angular velocity, leg contacts) is the env's
``environment_state`` (→ ``observation.environment_state``): LeRobot's ACT and Diffusion refuse inputs without an
image or an environment state, so datasets of this env train them as they are.

Success (``info["is_success"]``), a safe landing: the episode ends with the lander at rest (asleep in Box2D, which
is when gymnasium's +100 is paid), both legs touching the ground and its centre between the flags (|x| ≤ 0.2).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d.lunar_lander import LunarLander, heuristic

PAD_HALF_WIDTH = 0.2  # the flags stand at x = ±0.2 in the observation's units


class LunarLanderEnv(gym.Wrapper):
    """Dict observation ``environment_state`` and a safe landing as ``info["is_success"]``."""

    task_description = "Land the lander gently on the pad between the flags."

    def __init__(self, render_mode: str | None = "rgb_array"):
        super().__init__(LunarLander(render_mode=render_mode, continuous=True))
        inner = self.env.observation_space
        self.observation_space = gym.spaces.Dict(
            {"environment_state": gym.spaces.Box(inner.low, inner.high, dtype=np.float32)}
        )
        self.action_space = self.env.action_space
        self.metadata = dict(self.env.metadata)
        self.task = "lunarlander"
        self._state = np.zeros(8, dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed)
        self._state = np.asarray(obs, dtype=np.float32)
        info["is_success"] = False
        return {"environment_state": self._state}, info

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float32).reshape(-1), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._state = np.asarray(obs, dtype=np.float32)
        at_rest = terminated and not self.env.unwrapped.lander.awake
        legs_down = obs[6] > 0 and obs[7] > 0
        info["is_success"] = bool(at_rest and legs_down and abs(obs[0]) <= PAD_HALF_WIDTH)
        return {"environment_state": self._state}, float(reward), terminated, truncated, info

    def expert_action(self) -> np.ndarray:
        """Gymnasium's own heuristic controller on the current state."""
        return np.asarray(heuristic(self.env.unwrapped, self._state), dtype=np.float32)
