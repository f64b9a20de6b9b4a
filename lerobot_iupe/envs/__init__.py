"""The paper's environments: gymnasium ids ``lerobot_iupe/…`` and LeRobot env types."""

from lerobot_iupe.envs.classic import ClassicControlEnv, action_to_index
from lerobot_iupe.envs.configs import (
    AcrobotEnvConfig,
    CartPoleEnvConfig,
    IUPEEnvConfig,
    MazeEnvConfig,
    MountainCarEnvConfig,
    env_config_from_settings,
    register_gym_envs,
)
from lerobot_iupe.envs.maze import HELDOUT_LAYOUT_START, MazeEnv, MazeLayout

register_gym_envs()

__all__ = [
    "HELDOUT_LAYOUT_START",
    "AcrobotEnvConfig",
    "CartPoleEnvConfig",
    "ClassicControlEnv",
    "IUPEEnvConfig",
    "MazeEnv",
    "MazeEnvConfig",
    "MazeLayout",
    "MountainCarEnvConfig",
    "action_to_index",
    "env_config_from_settings",
    "register_gym_envs",
]
