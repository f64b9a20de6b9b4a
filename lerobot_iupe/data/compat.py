"""The one compatibility check between the things IUPE puts together — an expert dataset, pre-demonstrations, a
rollout env, a checkpoint: the same observation key and shape (as LeRobot stores it: (D,) or (H, W, C); cameras of
any height and width, as the policy resizes them, but the same channels), fps, env type, and action count
(discrete) or action dimensions (continuous). Each side is described by a ``DataSpec``; a
field one side does not know is not checked."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.configs import FeatureType
from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION

from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.envs.configs import env_config_from_settings, env_observation_keys


def _env_actions(env_cfg: EnvConfig | None) -> tuple[int | None, int | None]:
    """(action count, None) of a discrete env of this package, (None, action dimensions) of a continuous one."""
    if env_cfg is None:
        return None, None
    n_actions = getattr(env_cfg, "n_actions", 0)
    if n_actions:
        return n_actions, None
    return None, int(env_cfg.features[ACTION].shape[0])


@dataclass(frozen=True)
class DataSpec:
    """One side of a check; ``source`` names it in messages (e.g. "the expert dataset at data/x")."""

    source: str
    observation_key: str
    observation_shape: tuple[int, ...] | None = None  # None: the side has no such observation
    fps: int | None = None
    env_type: str | None = None
    n_actions: int | None = None
    action_dim: int | None = None  # continuous actions only
    available: tuple[str, ...] = ()  # the observation keys the side does have (for the message)


def dataset_spec(meta: LeRobotDatasetMetadata, key: str, source: str) -> DataSpec:
    """A dataset: its features and fps, and the env its ``meta/iupe.json`` records (when it has one)."""
    feature = meta.features.get(key)
    env = read_iupe_meta(meta.root).get("env")
    env_cfg = env_config_from_settings(env) if env else None
    n_actions, action_dim = _env_actions(env_cfg)
    action = meta.features.get(ACTION)
    if action is not None and action["dtype"].startswith("float"):
        n_actions, action_dim = None, int(action["shape"][0])
    return DataSpec(
        source=source,
        observation_key=key,
        observation_shape=tuple(feature["shape"]) if feature else None,
        fps=meta.fps,
        env_type=env_cfg.type if env_cfg else None,
        n_actions=n_actions,
        action_dim=action_dim,
        available=tuple(k for k in meta.features if k.startswith("observation.")),
    )


def env_spec(env_cfg: EnvConfig, key: str) -> DataSpec:
    """An env (any LeRobot env type): the observation its ``features_map`` maps to ``key``, fps, type, actions."""
    keys = env_observation_keys(env_cfg)
    env_key = {v: k for k, v in keys.items()}.get(key)
    feature = env_cfg.features.get(env_key) if env_key else None
    n_actions, action_dim = _env_actions(env_cfg)
    return DataSpec(
        source=f"env {env_cfg.type}",
        observation_key=key,
        observation_shape=tuple(feature.shape) if feature else None,
        fps=env_cfg.fps,
        env_type=env_cfg.type,
        n_actions=n_actions,
        action_dim=action_dim,
        available=tuple(keys.values()),
    )


def checkpoint_spec(config, key: str | None = None, source: str = "the checkpoint --policy.path") -> DataSpec:
    """An IUPE policy config: an observation it reads (default: the first; policies see images as (C, H, W)), the
    fps of its training data and its env (when it was trained with one)."""
    key = key or config.observation_key
    shape = tuple(config.input_features[key].shape)
    if config.input_features[key].type is FeatureType.VISUAL:
        shape = (shape[1], shape[2], shape[0])
    env_cfg = env_config_from_settings(config.env_settings) if config.env_settings else None
    return DataSpec(
        source=source,
        observation_key=key,
        observation_shape=shape,
        fps=config.fps or (env_cfg.fps if env_cfg else None),
        env_type=env_cfg.type if env_cfg else None,
        n_actions=config.n_actions or None,
        action_dim=config.action_dim if config.is_continuous else None,
        available=tuple(config.observation_keys),
    )


CHECKED = {"fps": "fps", "env_type": "env type", "n_actions": "number of actions", "action_dim": "action dimensions"}


def check_compatible(expected: DataSpec, actual: DataSpec) -> None:
    """Raise a ValueError naming both sides and what differs."""
    key = expected.observation_key
    if actual.observation_shape is None:
        raise ValueError(
            f"{expected.source} reads '{key}' but {actual.source} has no such observation "
            f"(it has {list(actual.available)})"
        )
    if expected.observation_shape is None:
        raise ValueError(
            f"{actual.source} has '{key}' but {expected.source} has no such observation "
            f"(it has {list(expected.available)})"
        )
    mine, theirs = expected.observation_shape, actual.observation_shape
    if len(mine) == 3 and len(theirs) == 3:  # cameras: any size is read at the working resolution
        if mine[-1] != theirs[-1]:
            raise ValueError(
                f"camera '{key}' has {theirs[-1]} channels in {actual.source} but {mine[-1]} in {expected.source}; "
                "they must match (any height and width are resized to the policy's --policy.resize_shape)"
            )
    elif mine != theirs:
        raise ValueError(
            f"'{key}' has shape {actual.observation_shape} in {actual.source} but {expected.observation_shape} in "
            f"{expected.source}; they must match"
        )
    for name, label in CHECKED.items():
        mine, theirs = getattr(expected, name), getattr(actual, name)
        if mine is not None and theirs is not None and mine != theirs:
            raise ValueError(f"{actual.source} and {expected.source} disagree on the {label}: {theirs!r} vs {mine!r}")
