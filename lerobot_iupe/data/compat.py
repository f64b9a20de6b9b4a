"""The one compatibility check between the things IUPE puts together — an expert dataset, pre-demonstrations, a
rollout env, a checkpoint: the same observation key and shape (as LeRobot stores it: (D,) or (H, W, C)), fps, env
type and action count. Each side is described by a ``DataSpec``; a field one side does not know is not checked."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.utils.constants import OBS_IMAGE

from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.envs.configs import IUPEEnvConfig, env_config_from_settings


@dataclass(frozen=True)
class DataSpec:
    """One side of a check; ``source`` names it in messages (e.g. "the expert dataset at data/x")."""

    source: str
    observation_key: str
    observation_shape: tuple[int, ...] | None = None  # None: the side has no such observation
    fps: int | None = None
    env_type: str | None = None
    n_actions: int | None = None
    available: tuple[str, ...] = ()  # the observation keys the side does have (for the message)


def dataset_spec(meta: LeRobotDatasetMetadata, key: str, source: str) -> DataSpec:
    """A dataset: its features and fps, and the env its ``meta/iupe.json`` records (when it has one)."""
    feature = meta.features.get(key)
    env = read_iupe_meta(meta.root).get("env")
    env_cfg = env_config_from_settings(env) if env else None
    return DataSpec(
        source=source,
        observation_key=key,
        observation_shape=tuple(feature["shape"]) if feature else None,
        fps=meta.fps,
        env_type=env_cfg.type if env_cfg else None,
        n_actions=env_cfg.n_actions if env_cfg else None,
        available=tuple(k for k in meta.features if k.startswith("observation.")),
    )


def env_spec(env_cfg: IUPEEnvConfig, key: str) -> DataSpec:
    """An env: the observation its ``features_map`` maps to ``key``, fps, type and action count."""
    env_key = {v: k for k, v in env_cfg.observation_keys.items()}.get(key)
    feature = env_cfg.features.get(env_key) if env_key else None
    return DataSpec(
        source=f"env {env_cfg.type}",
        observation_key=key,
        observation_shape=tuple(feature.shape) if feature else None,
        fps=env_cfg.fps,
        env_type=env_cfg.type,
        n_actions=env_cfg.n_actions,
        available=tuple(env_cfg.observation_keys.values()),
    )


def checkpoint_spec(config, source: str = "the checkpoint") -> DataSpec:
    """An IUPE policy config: the observation it reads (policies see images as (C, H, W)) and its env."""
    key = config.observation_key
    shape = tuple(config.input_features[key].shape)
    if key == OBS_IMAGE:
        shape = (shape[1], shape[2], shape[0])
    env_cfg = env_config_from_settings(config.env_settings) if config.env_settings else None
    return DataSpec(
        source=source,
        observation_key=key,
        observation_shape=shape,
        fps=env_cfg.fps if env_cfg else None,
        env_type=env_cfg.type if env_cfg else None,
        n_actions=config.n_actions or None,
        available=(key,),
    )


CHECKED = {"fps": "fps", "env_type": "env type", "n_actions": "number of actions"}


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
    if expected.observation_shape != actual.observation_shape:
        raise ValueError(
            f"'{key}' has shape {actual.observation_shape} in {actual.source} but {expected.observation_shape} in "
            f"{expected.source}; they must match"
        )
    for name, label in CHECKED.items():
        mine, theirs = getattr(expected, name), getattr(actual, name)
        if mine is not None and theirs is not None and mine != theirs:
            raise ValueError(f"{actual.source} and {expected.source} disagree on the {label}: {theirs!r} vs {mine!r}")
