"""Gymnasium's LunarLanderContinuous-v3, shaped for LeRobot (``--env.type=lunarlander``).

The 8-D state is split as LeRobot's conventions ask: the lander's own position, velocity, angle and angular
velocity (6) are ``agent_pos`` (→ ``observation.state``), its two leg contacts with the ground (2) the
``environment_state`` (→ ``observation.environment_state``). LeRobot's ACT refuses inputs without an image or an
environment state and reads ``observation.state`` in every forward pass, so datasets of this env train it as they
are. Policies that concatenate the keys in that order (IUPE does) see gymnasium's 8-D vector unchanged.

Success (``info["is_success"]``), a safe landing: the episode ends with the lander at rest (asleep in Box2D, which
is when gymnasium's +100 is paid), both legs touching the ground and its centre between the flags (|x| ≤ 0.2).

The goal the IUPE cycle checks at every step (``info["goal_reached"]``, the paper's "goal reached at any step"):
the lander stands on the pad, both legs touching between the flags, nearly still (|vx|, |vy| < 0.1) and its body
clear of the ground. A safe landing reaches it on the way to rest; a policy that keeps firing its engines after
standing on the pad reaches it and may still fail to come to rest.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from gymnasium.envs.box2d.lunar_lander import LunarLander, heuristic

from lerobot_iupe.envs.classic import ScaledRendering

PAD_HALF_WIDTH = 0.2  # the flags stand at x = ±0.2 in the observation's units
STILL_SPEED = 0.1  # |vx|, |vy| below this (observation units) count as standing still


class LunarLanderEnv(ScaledRendering, gym.Wrapper):
    """Dict observation ``agent_pos`` (6) + ``environment_state`` (2), a safe landing as ``info["is_success"]`` and
    standing on the pad as ``info["goal_reached"]``."""

    task_description = "Land the lander gently on the pad between the flags."

    def __init__(self, render_mode: str | None = "rgb_array"):
        super().__init__(LunarLander(render_mode=render_mode, continuous=True))
        inner = self.env.observation_space
        self.observation_space = gym.spaces.Dict(
            {
                "agent_pos": gym.spaces.Box(inner.low[:6], inner.high[:6], dtype=np.float32),
                "environment_state": gym.spaces.Box(inner.low[6:], inner.high[6:], dtype=np.float32),
            }
        )
        self.action_space = self.env.action_space
        self.metadata = dict(self.env.metadata)
        self.task = "lunarlander"
        self._state = np.zeros(8, dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed)
        self._state = np.asarray(obs, dtype=np.float32)
        info["is_success"] = info["goal_reached"] = False
        return self._observation(), info

    def step(self, action):
        action = np.clip(np.asarray(action, dtype=np.float32).reshape(-1), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._state = np.asarray(obs, dtype=np.float32)
        at_rest = terminated and not self.env.unwrapped.lander.awake
        legs_down = obs[6] > 0 and obs[7] > 0
        on_pad = legs_down and abs(obs[0]) <= PAD_HALF_WIDTH
        info["is_success"] = bool(at_rest and on_pad)
        still = abs(obs[2]) < STILL_SPEED and abs(obs[3]) < STILL_SPEED
        info["goal_reached"] = bool(on_pad and still and not self.env.unwrapped.game_over)
        return self._observation(), float(reward), terminated, truncated, info

    def _observation(self) -> dict[str, np.ndarray]:
        return {"agent_pos": self._state[:6].copy(), "environment_state": self._state[6:].copy()}

    def expert_action(self) -> np.ndarray:
        """Gymnasium's own heuristic controller on the current state."""
        return np.asarray(heuristic(self.env.unwrapped, self._state), dtype=np.float32)
