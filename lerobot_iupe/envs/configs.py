"""LeRobot env types ``cartpole``, ``acrobot``, ``mountaincar`` and ``maze`` (``--env.type=…``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

from lerobot_iupe.envs.maze import HELDOUT_LAYOUT_START, default_max_steps

GYM_NAMESPACE = "lerobot_iupe"


@dataclass
class IUPEEnvConfig(EnvConfig):
    """Common part: a gym id registered by this package, a time limit and a discrete action count."""

    n_actions: int = 0

    @property
    def package_name(self) -> str:
        """LeRobot's gym id is ``<package_name>/<task>``: the ids this package registers."""
        return GYM_NAMESPACE

    @property
    def max_episode_steps(self) -> int:
        raise NotImplementedError

    @property
    def is_image(self) -> bool:
        return OBS_IMAGE in self.features_map.values()

    @property
    def observation_keys(self) -> dict[str, str]:
        """Env observation key → dataset/policy key (``agent_pos`` → ``observation.state``), from ``features_map``."""
        return {env_key: key for env_key, key in self.features_map.items() if key != ACTION}

    def validate(self) -> None:
        """Raise a ValueError naming the flag when a setting is out of range (draccus hides __post_init__ errors)."""

    def settings(self) -> dict:
        """What a dataset records so a consumer can rebuild this exact environment (config fields)."""
        raise NotImplementedError

    def make(self) -> gym.Env:
        """One environment with LeRobot's wrappers order (time limit outside)."""
        self.validate()
        return gym.make(self.gym_id, disable_env_checker=self.disable_env_checker, **self.gym_kwargs)


def _vector_features(state_dim: int) -> dict[str, PolicyFeature]:
    return {
        ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(1,)),
        "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
    }


VECTOR_FEATURES_MAP = {ACTION: ACTION, "agent_pos": OBS_STATE}


@dataclass
class ClassicEnvConfig(IUPEEnvConfig):
    episode_length: int = 500

    @property
    def max_episode_steps(self) -> int:
        return self.episode_length

    @property
    def gym_kwargs(self) -> dict:
        return {"max_episode_steps": self.episode_length}

    def settings(self) -> dict:
        return {"type": self.type, "episode_length": self.episode_length}


@EnvConfig.register_subclass("cartpole")
@dataclass
class CartPoleEnvConfig(ClassicEnvConfig):
    task: str | None = "CartPole-v1"
    fps: int = 50
    n_actions: int = 2
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _vector_features(4))
    features_map: dict[str, str] = field(default_factory=lambda: dict(VECTOR_FEATURES_MAP))


@EnvConfig.register_subclass("acrobot")
@dataclass
class AcrobotEnvConfig(ClassicEnvConfig):
    task: str | None = "Acrobot-v1"
    fps: int = 15
    n_actions: int = 3
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _vector_features(6))
    features_map: dict[str, str] = field(default_factory=lambda: dict(VECTOR_FEATURES_MAP))


@EnvConfig.register_subclass("mountaincar")
@dataclass
class MountainCarEnvConfig(ClassicEnvConfig):
    task: str | None = "MountainCar-v0"
    fps: int = 30
    n_actions: int = 3
    episode_length: int = 200
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _vector_features(2))
    features_map: dict[str, str] = field(default_factory=lambda: dict(VECTOR_FEATURES_MAP))


@EnvConfig.register_subclass("maze")
@dataclass
class MazeEnvConfig(IUPEEnvConfig):
    """Image maze. ``layouts``: ``demo`` draws from ids ``[0, num_layouts)`` (the demonstration layouts),
    ``heldout`` from ``[1_000_000, 1_000_000 + num_layouts)``. ``max_steps`` 0 means ``10 · size²``."""

    task: str | None = "Maze-v0"
    fps: int = 10
    n_actions: int = 4
    size: int = 5
    image_size: int = 64
    layouts: str = "demo"
    num_layouts: int = 100
    max_steps: int = 0
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=lambda: {ACTION: ACTION, "pixels": OBS_IMAGE})

    def __post_init__(self):
        self.features = {
            ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(1,)),
            "pixels": PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3)),
        }

    def validate(self) -> None:
        if self.size < 2:
            raise ValueError(f"--env.size must be at least 2 (got {self.size}); the paper uses 3, 5 and 10")
        if self.layouts not in ("demo", "heldout"):
            raise ValueError(f"--env.layouts must be 'demo' or 'heldout', got {self.layouts!r}")
        if self.num_layouts < 1:
            raise ValueError(f"--env.num_layouts must be at least 1, got {self.num_layouts}")
        if self.image_size < 2 * self.size + 1:
            raise ValueError(f"--env.image_size={self.image_size} cannot show a {self.size}x{self.size} maze")

    @property
    def layout_start(self) -> int:
        return 0 if self.layouts == "demo" else HELDOUT_LAYOUT_START

    @property
    def max_episode_steps(self) -> int:
        return self.max_steps or default_max_steps(self.size)

    @property
    def gym_kwargs(self) -> dict:
        return {
            "size": self.size,
            "image_size": self.image_size,
            "layout_start": self.layout_start,
            "num_layouts": self.num_layouts,
            "max_episode_steps": self.max_episode_steps,
        }

    def settings(self) -> dict:
        return {"type": self.type, "size": self.size, "image_size": self.image_size, "max_steps": self.max_steps}


def register_gym_envs() -> None:
    """Register the package's gymnasium ids (idempotent)."""
    entries = {
        "CartPole-v1": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "cartpole"}, 500),
        "Acrobot-v1": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "acrobot"}, 500),
        "MountainCar-v0": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "mountaincar"}, 200),
        "Maze-v0": ("lerobot_iupe.envs.maze:MazeEnv", {}, None),
    }
    for task, (entry_point, kwargs, max_steps) in entries.items():
        env_id = f"{GYM_NAMESPACE}/{task}"
        if env_id not in gym.registry:
            gym.register(env_id, entry_point=entry_point, kwargs=kwargs, max_episode_steps=max_steps)


def env_config_from_settings(settings: dict) -> EnvConfig:
    """The env config a dataset's ``meta/iupe.json`` records (``IUPEEnvConfig.settings()``, the other way)."""
    fields = {k: v for k, v in settings.items() if k != "type"}
    return EnvConfig.get_choice_class(settings["type"])(**fields)
