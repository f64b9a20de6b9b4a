"""Demonstration datasets: play a built-in agent in one of the package's envs and record a LeRobot v3.0 dataset.

Episode layout (T steps → T + 1 frames, so that every transition (s_t, s_{t+1}) is in the data):
frame t < T holds ``s_t``, the action ``a_t`` (if kept), and ``next.reward``/``next.done``/``next.success`` of
that step; the last frame holds the terminal observation ``s_T`` with reward 0, ``next.done`` True and a
placeholder action 0. Learners that need an action drop the last frame of each episode.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lerobot.configs import FeatureType
from lerobot.datasets import LeRobotDataset
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION
from tqdm.auto import tqdm

from lerobot_iupe.data.storage import (
    WrittenDataset,
    dataset_lock,
    no_image_embedding_without_images,
    resolve_root,
    staged_directory,
    write_iupe_meta,
)
from lerobot_iupe.envs.configs import IUPEEnvConfig, action_names, env_observation
from lerobot_iupe.envs.rollout import Episode, agent_act, run_episodes
from lerobot_iupe.experts import AGENTS, make_agent

REWARD, DONE, SUCCESS = "next.reward", "next.done", "next.success"
ENV_TYPES = ("cartpole", "acrobot", "mountaincar", "maze", "lunarlander", "so101_pickplace")
# Flags that were top-level before they took LeRobot's names.
RENAMED_FLAGS = {"--push_to_hub": "--dataset.push_to_hub"}


@dataclass
class CollectConfig:
    env: EnvConfig | None = None
    dataset: WrittenDataset = field(default_factory=WrittenDataset)
    # Which built-in agent plays: "expert", "random" (uniform actions) or "play" (goal-agnostic play where uniform
    # actions never reach the expert's states: so101_pickplace). Pre-demonstrations come from random or play.
    agent: str = "expert"
    # Number of episodes to record.
    episodes: int = 20
    # Episode i is reset with seed `seed + i` (mazes: on layout `seed + i`).
    seed: int = 0
    # Keep the expert's actions (only the supervised BC baseline needs them). Random and play datasets keep them.
    keep_actions: bool = False
    # Maze only: start each episode from a random cell (random pre-demonstrations cover the maze better).
    random_start: bool = False
    # Envs with cameras: store frames as an MP4 video (true) or as PNG images inside the parquet files (false).
    # LeRobot's training loader decodes a video frame per item (~2.4 ms with pyav) and a small PNG ~10x faster.
    video: bool = True
    # Replace an existing dataset root (the old one is kept until the new one is complete).
    overwrite: bool = False

    def validate(self) -> None:
        if self.env is None:
            raise ValueError(f"--env.type is required: one of {', '.join(ENV_TYPES)}")
        if not isinstance(self.env, IUPEEnvConfig):
            raise ValueError(
                f"--env.type={self.env.type} is not an env of this package (its agents live here); "
                f"use one of {', '.join(ENV_TYPES)}"
            )
        self.env.validate()
        if self.agent not in AGENTS:
            raise ValueError(f"--agent={self.agent} is not known; use one of {list(AGENTS)}")
        if self.episodes <= 0:
            raise ValueError(f"--episodes must be a positive number of episodes, got {self.episodes}")
        if self.random_start and not self.env.is_image:
            raise ValueError("--random_start=true only applies to --env.type=maze")
        if not self.video and not self.env.has_cameras:
            raise ValueError(
                "--video=false only applies to envs with cameras (--env.type=maze, or so101_pickplace with "
                "--env.image_obs=true)"
            )

    @property
    def stores_actions(self) -> bool:
        return self.agent != "expert" or self.keep_actions


def dataset_features(env_cfg: IUPEEnvConfig, with_actions: bool, video: bool = True) -> dict:
    """LeRobot feature spec of a demonstration dataset of this env."""
    features = {}
    for env_key, key in env_cfg.observation_keys.items():
        shape = tuple(env_cfg.features[env_key].shape)
        if env_cfg.features[env_key].type is FeatureType.VISUAL:
            names = ["height", "width", "channels"]
            features[key] = {"dtype": "video" if video else "image", "shape": shape, "names": names}
        else:
            features[key] = {"dtype": "float32", "shape": shape, "names": env_cfg.state_names(env_key)}
    if with_actions and env_cfg.n_actions:
        features[ACTION] = {"dtype": "int64", "shape": (1,), "names": ["action_id"]}
    elif with_actions:
        features[ACTION] = {
            "dtype": "float32",
            "shape": tuple(env_cfg.features[ACTION].shape),
            "names": action_names(env_cfg),
        }
    features[REWARD] = {"dtype": "float32", "shape": (1,), "names": None}
    features[DONE] = {"dtype": "bool", "shape": (1,), "names": None}
    features[SUCCESS] = {"dtype": "bool", "shape": (1,), "names": None}
    return features


def _observation_entry(env_cfg: IUPEEnvConfig, observation: dict) -> dict:
    """The dataset keys of an env observation; vectors as float32 (``dataset_features``), images as they come."""
    return {
        key: env_observation(observation, env_key)
        if env_cfg.features[env_key].type is FeatureType.VISUAL
        else np.asarray(env_observation(observation, env_key), dtype=np.float32)
        for env_key, key in env_cfg.observation_keys.items()
    }


def _action_entry(env_cfg: IUPEEnvConfig, action) -> np.ndarray:
    """An action as stored: the id as int64 (1,) for a discrete env, float32 (action_dim,) for a continuous one."""
    if env_cfg.n_actions:
        return np.array([int(np.asarray(action).reshape(-1)[0])], dtype=np.int64)
    return np.asarray(action, dtype=np.float32).reshape(env_cfg.features[ACTION].shape)


def episode_frames(env_cfg: IUPEEnvConfig, episode: Episode, task: str, with_actions: bool) -> Iterator[dict]:
    """The T + 1 frames of an episode of T steps (see the module's docstring)."""
    success = False
    for t, action in enumerate(episode.actions):
        success |= episode.successes[t]
        frame = _observation_entry(env_cfg, episode.observations[t])
        if with_actions:
            frame[ACTION] = _action_entry(env_cfg, action)
        done = t == len(episode) - 1
        reward = np.array([episode.rewards[t]], dtype=np.float32)
        yield {**frame, REWARD: reward, DONE: np.array([done]), SUCCESS: np.array([success]), "task": task}
    last = _observation_entry(env_cfg, episode.observations[-1])
    if with_actions:
        last[ACTION] = _action_entry(env_cfg, np.zeros(env_cfg.features[ACTION].shape))
    yield {**last, REWARD: np.zeros(1, np.float32), DONE: np.array([True]), SUCCESS: np.array([success]), "task": task}


def record_episodes(dataset: LeRobotDataset, cfg: CollectConfig) -> dict:
    """Play ``cfg.episodes`` episodes into ``dataset``; returns per-episode statistics."""
    env_cfg = cfg.env
    env = env_cfg.make()
    act = agent_act([env], make_agent(env_cfg.type, cfg.agent))
    task = env.get_wrapper_attr("task_description")
    returns, successes, lengths, layouts = [], [], [], []
    progress = tqdm(range(cfg.episodes), desc=f"{env_cfg.type} {cfg.agent}", unit="episode")
    for episode_index in progress:
        seed = cfg.seed + episode_index
        options = {"layout_id": seed, "random_start": cfg.random_start} if env_cfg.is_image else None
        episode = run_episodes([env], act, [seed], [options])[0]
        for frame in episode_frames(env_cfg, episode, task, cfg.stores_actions):
            dataset.add_frame(frame)
        dataset.save_episode()
        returns.append(episode.total_reward)
        successes.append(episode.success)
        lengths.append(len(episode))
        if env_cfg.is_image:
            layouts.append(int(episode.info["layout_id"]))
        progress.set_postfix(mean_return=f"{np.mean(returns):.2f}")
    env.close()
    return {"returns": returns, "successes": successes, "lengths": lengths, "layout_ids": layouts}


def collect(cfg: CollectConfig) -> tuple[Path, dict]:
    """Record the dataset described by ``cfg``; nothing is written at the root until it is complete."""
    cfg.validate()
    root = resolve_root(cfg.dataset.repo_id, cfg.dataset.root)
    start = time.perf_counter()
    with dataset_lock(root), staged_directory(root, cfg.overwrite) as staged:
        dataset = LeRobotDataset.create(
            repo_id=cfg.dataset.repo_id,
            fps=cfg.env.fps,
            features=dataset_features(cfg.env, cfg.stores_actions, cfg.video),
            root=staged,
            robot_type=cfg.env.type,
            use_videos=cfg.env.has_cameras and cfg.video,
        )
        try:
            with no_image_embedding_without_images():
                stats = record_episodes(dataset, cfg)
        finally:
            dataset.finalize()
        shutil.rmtree(staged / "images", ignore_errors=True)  # frame scratch space, empty once videos are encoded
        returns = np.asarray(stats["returns"])
        meta = {
            "env": cfg.env.settings(),
            "agent": cfg.agent,
            "episodes": cfg.episodes,
            "seeds": [cfg.seed + i for i in range(cfg.episodes)],
            "has_actions": cfg.stores_actions,
            "random_start": cfg.random_start,
            "mean_return": float(returns.mean()),
            "std_return": float(returns.std()),
            "success_rate": float(np.mean(stats["successes"])),
            "episode_returns": [float(r) for r in returns],
        }
        if cfg.env.is_image:
            meta["layout_ids"] = stats["layout_ids"]
        write_iupe_meta(staged, meta)
    meta["seconds"] = time.perf_counter() - start
    return root, meta
