"""The SO-101 pick-and-place task of the ``lerobot_env_so101`` plugin, with its success where LeRobot reads it.

The plugin's env reports success as ``info["succeed"]``; LeRobot's evaluation reads ``info["is_success"]`` and so
scores it 0%. This wrapper adds ``is_success`` (and a task description) around the unmodified plugin env, and
carries the plugin's scripted pick-and-place controller as the expert (it keeps a phase across steps, so it lives
with the env and restarts on every reset).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv
from lerobot_env_so101.scripted.pick_place import PickPlaceController


class SO101PickPlaceEnv(gym.Wrapper):
    """``lerobot_env_so101``'s SO101PickPlace env with ``info["is_success"]`` (from its ``succeed``)."""

    task_description = "Pick up the cube and place it on the goal."

    def __init__(self, action_scale: float = 0.025, random_block_position: bool = True, image_obs: bool = False,
                 render_mode: str = "rgb_array"):  # fmt: skip
        super().__init__(
            SO101PickPlaceGymEnv(
                action_scale=action_scale,
                random_block_position=random_block_position,
                image_obs=image_obs,
                render_mode=render_mode,
            )
        )
        self.task = "so101_pickplace"
        self._controller = PickPlaceController(action_scale=action_scale)
        self._success = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed)
        self._controller.reset()
        self._success = False
        info["is_success"] = False
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float32).reshape(-1))
        self._success |= bool(info.get("succeed", False))
        info["is_success"] = self._success
        return obs, reward, terminated, truncated, info

    def expert_action(self) -> np.ndarray:
        """The plugin's scripted controller (hover, descend, close, lift, traverse, lower, open, retreat)."""
        env = self.env.unwrapped
        block = env.data.sensor("block_pos").data
        return self._controller.act(env.ik_point_pos, block, env.goal_pos)
