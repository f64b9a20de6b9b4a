"""Gymnasium's CartPole, Acrobot and MountainCar, shaped for LeRobot.

LeRobot's eval loop wants dict observations (``agent_pos``), sends float actions of shape ``(action_dim,)``,
reads ``info["is_success"]`` and a ``task_description``. This wrapper provides exactly that around the
unmodified gymnasium dynamics; the time limit is added by ``gym.make`` (``max_episode_steps``).
"""

from __future__ import annotations

from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium.envs.classic_control import AcrobotEnv, CartPoleEnv, MountainCarEnv

CARTPOLE_SUCCESS_STEPS = 195
# lerobot-eval holds every rendered frame of a batch in memory (up to 10 episodes × their steps): at gymnasium's
# 600×400 the README's CartPole evaluation peaked at 8.9 GB (LunarLander's 1,000 steps would hold 7.2 GB of frames).
# Half size keeps the drawing and needs a quarter of that.
RENDER_SCALE = 0.5


def action_to_index(action: Any, n_actions: int) -> int:
    """Turn LeRobot's float action (shape ``(1,)`` or scalar) into a discrete action id, refusing bad ids."""
    value = float(np.asarray(action, dtype=np.float64).reshape(-1)[0])
    index = int(np.rint(value))
    if not 0 <= index < n_actions or abs(value - index) > 1e-3:
        raise ValueError(f"action {value!r} is not a valid action id in [0, {n_actions - 1}]")
    return index


class ScaledRendering:
    """``render()`` of a wrapped gymnasium env at ``RENDER_SCALE`` of its size, area-averaged so that its 1-pixel
    lines stay (CartPole's track, Acrobot's goal line)."""

    def render(self) -> np.ndarray | None:
        frame = self.env.render()
        if frame is None:
            return None
        height, width = frame.shape[:2]
        size = (round(width * RENDER_SCALE), round(height * RENDER_SCALE))
        return cv2.resize(frame, size, interpolation=cv2.INTER_AREA)


class ClassicControlEnv(ScaledRendering, gym.Wrapper):
    """Dict-observation wrapper with the paper's goal criterion as ``info["is_success"]``."""

    TASKS = {
        "cartpole": (CartPoleEnv, "Keep the pole upright by pushing the cart left or right."),
        "acrobot": (AcrobotEnv, "Swing the tip of the acrobot above the line."),
        "mountaincar": (MountainCarEnv, "Drive the car up the right hill to the flag."),
    }

    def __init__(self, name: str, render_mode: str | None = "rgb_array"):
        if name not in self.TASKS:
            raise ValueError(f"unknown classic-control env {name!r}; expected one of {sorted(self.TASKS)}")
        env_cls, self.task_description = self.TASKS[name]
        super().__init__(env_cls(render_mode=render_mode))
        self.name = name
        self.task = name
        inner = self.env.observation_space
        self.observation_space = gym.spaces.Dict({"agent_pos": gym.spaces.Box(inner.low, inner.high, dtype=np.float32)})
        self.action_space = self.env.action_space
        self.metadata = dict(self.env.metadata)
        self._steps = 0
        self._success = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed)
        self._steps, self._success = 0, False
        info["is_success"] = False
        return {"agent_pos": np.asarray(obs, dtype=np.float32)}, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action_to_index(action, self.action_space.n))
        self._steps += 1
        if self.name == "cartpole":
            self._success |= self._steps >= CARTPOLE_SUCCESS_STEPS
        else:
            self._success |= bool(terminated)
        info["is_success"] = self._success
        return {"agent_pos": np.asarray(obs, dtype=np.float32)}, float(reward), terminated, truncated, info
