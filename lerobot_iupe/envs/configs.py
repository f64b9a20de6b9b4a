"""LeRobot env types of this package (``--env.type=…``): the paper's discrete ``cartpole``, ``acrobot``,
``mountaincar`` and ``maze``, and the continuous ``lunarlander`` and ``so101_pickplace``; and what the package reads
of any LeRobot env config (``env_observation_keys``, ``env_settings``, ``make_envs``)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import gymnasium as gym
import numpy as np
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.factory import make_env
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGE, OBS_IMAGES, OBS_STATE

from lerobot_iupe.envs.maze import HELDOUT_LAYOUT_START, default_max_steps

GYM_NAMESPACE = "lerobot_iupe"
SO101_ARM_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")


@dataclass
class IUPEEnvConfig(EnvConfig):
    """Common part: a gym id registered by this package, a time limit, and a discrete action count (0 for a
    continuous ``Box`` action, whose shape is ``features["action"]``)."""

    n_actions: int = 0
    # What each entry of a vector observation is, by env key, in LeRobot's "<joint>.pos" style: the names datasets
    # give their features, so that LeRobot's tools and third-party checkers can read them.
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {}

    def state_names(self, env_key: str) -> list[str]:
        return list(self.STATE_NAMES[env_key])

    @property
    def package_name(self) -> str:
        """LeRobot's gym id is ``<package_name>/<task>``: the ids this package registers."""
        return GYM_NAMESPACE

    @property
    def max_episode_steps(self) -> int:
        raise NotImplementedError

    @property
    def is_image(self) -> bool:
        """The maze's image observation (layouts, random starts)."""
        return OBS_IMAGE in self.features_map.values()

    @property
    def has_cameras(self) -> bool:
        return any(self.features[k].type is FeatureType.VISUAL for k in self.observation_keys)

    @property
    def observation_keys(self) -> dict[str, str]:
        return env_observation_keys(self)

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
STATE_ENV_FEATURES_MAP = {ACTION: ACTION, "agent_pos": OBS_STATE, "environment_state": OBS_ENV_STATE}


def state_env_features(action_dim: int, state_dim: int, env_dim: int) -> dict[str, PolicyFeature]:
    """A continuous ``Box`` action, ``agent_pos`` (→ observation.state) and ``environment_state``."""
    return {
        ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,)),
        "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
        "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(env_dim,)),
    }


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
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {"agent_pos": ("cart.pos", "cart.vel", "pole.pos", "pole.vel")}
    fps: int = 50
    n_actions: int = 2
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _vector_features(4))
    features_map: dict[str, str] = field(default_factory=lambda: dict(VECTOR_FEATURES_MAP))


@EnvConfig.register_subclass("acrobot")
@dataclass
class AcrobotEnvConfig(ClassicEnvConfig):
    task: str | None = "Acrobot-v1"
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {
        "agent_pos": ("joint1.cos", "joint1.sin", "joint2.cos", "joint2.sin", "joint1.vel", "joint2.vel")
    }
    fps: int = 15
    n_actions: int = 3
    features: dict[str, PolicyFeature] = field(default_factory=lambda: _vector_features(6))
    features_map: dict[str, str] = field(default_factory=lambda: dict(VECTOR_FEATURES_MAP))


@EnvConfig.register_subclass("mountaincar")
@dataclass
class MountainCarEnvConfig(ClassicEnvConfig):
    task: str | None = "MountainCar-v0"
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {"agent_pos": ("car.pos", "car.vel")}
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


@EnvConfig.register_subclass("lunarlander")
@dataclass
class LunarLanderEnvConfig(ClassicEnvConfig):
    """Gymnasium's LunarLanderContinuous-v3: 2-D action [main engine, lateral engines] in [-1, 1]; the lander's
    kinematics (6) are ``observation.state``, its leg contacts (2) ``observation.environment_state`` (see
    ``envs/lunar.py`` for why, and for the safe-landing success rule)."""

    task: str | None = "LunarLanderContinuous-v3"
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {
        "agent_pos": ("lander.x", "lander.y", "lander.vel_x", "lander.vel_y", "lander.angle", "lander.angular_vel"),
        "environment_state": ("left_leg.contact", "right_leg.contact"),
    }
    fps: int = 50
    episode_length: int = 1000
    features: dict[str, PolicyFeature] = field(default_factory=lambda: state_env_features(2, 6, 2))
    features_map: dict[str, str] = field(default_factory=lambda: dict(STATE_ENV_FEATURES_MAP))
    action_names: tuple[str, ...] = ("main_engine", "lateral_engines")


@EnvConfig.register_subclass("so101_pickplace")
@dataclass
class SO101PickPlaceEnvConfig(ClassicEnvConfig):
    """The ``lerobot_env_so101`` plugin's pick-and-place task (random block and goal positions) with its success
    as ``info["is_success"]``: 4-D action [dx, dy, dz, grasp], ``agent_pos`` (14) → ``observation.state``,
    ``environment_state`` (block and goal positions, 6) → ``observation.environment_state``."""

    task: str | None = "SO101PickPlace-v0"
    # The plugin's robot state: its five arm joints' positions and velocities, the gripper's commanded opening
    # (-1 closed … 1 open), the end effector's position; then the block's and the goal's positions.
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {
        "agent_pos": (
            *(f"{joint}.pos" for joint in SO101_ARM_JOINTS),
            *(f"{joint}.vel" for joint in SO101_ARM_JOINTS),
            "gripper.pos",
            "ee.x",
            "ee.y",
            "ee.z",
        ),  # fmt: skip
        "environment_state": ("block.x", "block.y", "block.z", "goal.x", "goal.y", "goal.z"),
    }
    fps: int = 10
    # The plugin's own cap: cloned policies are slower than the scripted expert (47 steps on average) and lost
    # about 0.1 success at a 100-step cap.
    episode_length: int = 300
    action_scale: float = 0.025
    random_block_position: bool = True
    features: dict[str, PolicyFeature] = field(default_factory=lambda: state_env_features(4, 14, 6))
    features_map: dict[str, str] = field(default_factory=lambda: dict(STATE_ENV_FEATURES_MAP))
    action_names: tuple[str, ...] = ("dx", "dy", "dz", "grasp")
    # The front camera (image_size × image_size RGB) → observation.images.front, in place of environment_state (the
    # plugin's image observation: the block and goal are then seen, not read). Rendered by MuJoCo offscreen (EGL).
    image_obs: bool = False
    image_size: int = 64
    # environment_state also carries the block and the goal seen from the end effector (block − ee, goal − ee; 12
    # entries), as robot-learning suites give object-relative positions: a policy then reads "how far above the
    # block" directly instead of composing it from absolute coordinates (benchmarks/findings.md measures it).
    relative_positions: bool = False
    RELATIVE_NAMES: ClassVar[tuple[str, ...]] = tuple(
        f"{part}_from_ee.{a}" for part in ("block", "goal") for a in "xyz"
    )

    def __post_init__(self):
        if self.relative_positions and not self.image_obs:
            self.features = self.features | {"environment_state": PolicyFeature(type=FeatureType.ENV, shape=(12,))}
        if self.image_obs:
            camera = PolicyFeature(type=FeatureType.VISUAL, shape=(self.image_size, self.image_size, 3))
            self.features = {k: v for k, v in self.features.items() if k != "environment_state"} | {"front": camera}
            self.features_map = {k: v for k, v in self.features_map.items() if k != "environment_state"} | {
                "front": f"{OBS_IMAGES}.front"
            }

    def validate(self) -> None:
        if self.action_scale <= 0:
            raise ValueError(f"--env.action_scale must be positive (metres per unit action), got {self.action_scale}")
        if self.episode_length < 1:
            raise ValueError(f"--env.episode_length must be at least 1, got {self.episode_length}")
        if self.image_size < 16:
            raise ValueError(f"--env.image_size must be at least 16 pixels, got {self.image_size}")
        if self.image_obs and self.relative_positions:
            raise ValueError(
                "--env.relative_positions=true extends environment_state, which --env.image_obs=true replaces by the "
                "camera (the block is then seen, not read): pass one of them"
            )

    def state_names(self, env_key: str) -> list[str]:
        names = super().state_names(env_key)
        relative = env_key == "environment_state" and self.relative_positions
        return names + list(self.RELATIVE_NAMES) if relative else names

    def _task_settings(self) -> dict:
        """The plugin env's settings beyond the time limit: ``gym_kwargs`` and ``settings`` both carry them (an
        option left at its default is left out, so settings recorded before it existed read the same)."""
        camera = {"image_obs": True, "image_size": self.image_size} if self.image_obs else {}
        relative = {"relative_positions": True} if self.relative_positions else {}
        return {
            "action_scale": self.action_scale, "random_block_position": self.random_block_position, **camera,
            **relative,
        }  # fmt: skip

    @property
    def gym_kwargs(self) -> dict:
        return {**super().gym_kwargs, **self._task_settings()}

    def settings(self) -> dict:
        return {**super().settings(), **self._task_settings()}


def register_gym_envs() -> None:
    """Register the package's gymnasium ids (idempotent)."""
    entries = {
        "CartPole-v1": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "cartpole"}, 500),
        "Acrobot-v1": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "acrobot"}, 500),
        "MountainCar-v0": ("lerobot_iupe.envs.classic:ClassicControlEnv", {"name": "mountaincar"}, 200),
        "Maze-v0": ("lerobot_iupe.envs.maze:MazeEnv", {}, None),
        "LunarLanderContinuous-v3": ("lerobot_iupe.envs.lunar:LunarLanderEnv", {}, 1000),
        "SO101PickPlace-v0": ("lerobot_iupe.envs.so101:SO101PickPlaceEnv", {}, 300),
        "MetaWorldState-v0": ("lerobot_iupe.envs.metaworld:MetaWorldStateEnv", {}, 500),
    }
    for task, (entry_point, kwargs, max_steps) in entries.items():
        env_id = f"{GYM_NAMESPACE}/{task}"
        if env_id not in gym.registry:
            gym.register(env_id, entry_point=entry_point, kwargs=kwargs, max_episode_steps=max_steps)


def env_config_from_settings(settings: dict) -> EnvConfig:
    """The env config a dataset's ``meta/iupe.json`` records (``env_settings``, the other way)."""
    fields = {k: v for k, v in settings.items() if k != "type"}
    return EnvConfig.get_choice_class(settings["type"])(**fields)


def env_cli_flags(settings: dict) -> list[str]:
    """The ``--env.*`` flags of the LeRobot CLIs that build the env of ``settings`` (booleans as draccus reads them)."""
    return [f"--env.{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in settings.items()]


def env_settings(env_cfg: EnvConfig) -> dict:
    """What rebuilds ``env_cfg`` with ``env_config_from_settings``: this package's ``settings()``, or for any other
    LeRobot env type its plain (number, string, bool) config fields."""
    if isinstance(env_cfg, IUPEEnvConfig):
        return env_cfg.settings()
    plain = (int, float, str, bool, type(None))
    fields = {f.name: getattr(env_cfg, f.name) for f in dataclasses.fields(env_cfg) if f.init}
    return {"type": env_cfg.type, **{k: v for k, v in fields.items() if isinstance(v, plain)}}


def env_observation_keys(env_cfg: EnvConfig) -> dict[str, str]:
    """Env observation key → dataset/policy key (``agent_pos`` → ``observation.state``), from ``features_map``."""
    return {env_key: key for env_key, key in env_cfg.features_map.items() if key != ACTION}


def env_observation(observation: dict, env_key: str) -> np.ndarray:
    """One entry of an env's dict observation; cameras may sit under ``pixels`` (``{"pixels": {"top": …}}``)."""
    if env_key in observation:
        return observation[env_key]
    return observation["pixels"][env_key]


def action_names(env_cfg: EnvConfig) -> list[str]:
    names = getattr(env_cfg, "action_names", None)
    dim = int(env_cfg.features[ACTION].shape[0])
    return list(names) if names else [f"a{i}" for i in range(dim)]


def make_envs(env_cfg: EnvConfig, n: int) -> list[gym.Env]:
    """``n`` single envs made by LeRobot's ``make_env`` (as ``lerobot-eval`` makes them; it imports the env's
    package when its gym id is not registered yet), each reset and stepped on its own."""
    validate = getattr(env_cfg, "validate", None)
    if validate is not None:
        validate()
    vector = make_env(env_cfg, n_envs=n)[env_cfg.type][0]
    return list(vector.envs)


def action_space_of(env_cfg: EnvConfig) -> gym.spaces.Space:
    env = make_envs(env_cfg, 1)[0]
    space = env.action_space
    env.close()
    return space
