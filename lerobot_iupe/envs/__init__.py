"""The package's environments: gymnasium ids ``lerobot_iupe/…`` and LeRobot env types (the paper's, LunarLander,
SO-101, Meta-World observed as state)."""

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
from lerobot_iupe.envs.metaworld_config import METAWORLD_MT10, MetaWorldStateEnvConfig

register_gym_envs()

__all__ = [
    "HELDOUT_LAYOUT_START",
    "METAWORLD_MT10",
    "AcrobotEnvConfig",
    "CartPoleEnvConfig",
    "ClassicControlEnv",
    "IUPEEnvConfig",
    "MazeEnv",
    "MazeEnvConfig",
    "MazeLayout",
    "MetaWorldStateEnvConfig",
    "MountainCarEnvConfig",
    "action_to_index",
    "env_config_from_settings",
    "register_gym_envs",
]
