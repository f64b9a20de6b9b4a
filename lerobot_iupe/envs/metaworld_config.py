"""LeRobot env type ``metaworld_state``: one Meta-World task through LeRobot's own Meta-World env, observed as state
(the env itself: ``envs/metaworld.py``, imported only when an env is made, since it imports MuJoCo)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import cache
from importlib.resources import files
from typing import ClassVar

from lerobot.configs import PolicyFeature
from lerobot.envs.configs import EnvConfig

from lerobot_iupe.envs.configs import GYM_NAMESPACE, STATE_ENV_FEATURES_MAP, ClassicEnvConfig, state_env_features

# Meta-World's MT10 (Yu et al., 2019), the ten tasks the package reports: LeRobot names no such group.
METAWORLD_MT10 = (
    "reach-v3", "push-v3", "pick-place-v3", "door-open-v3", "drawer-open-v3", "drawer-close-v3",
    "button-press-topdown-v3", "peg-insert-side-v3", "window-open-v3", "window-close-v3",
)  # fmt: skip
METAWORLD_OBJECT = ("x", "y", "z", "qw", "qx", "qy", "qz")


@cache
def metaworld_tasks() -> tuple[str, ...]:
    """Meta-World's task names as LeRobot's ``metaworld`` env lists them (its ``metaworld_config.json``), read
    without importing Meta-World and MuJoCo."""
    config = json.loads(files("lerobot.envs").joinpath("metaworld_config.json").read_text())
    return tuple(config["TASK_DESCRIPTIONS"])


def check_metaworld_task(task: str | None) -> None:
    """Raise a ValueError naming ``--env.task`` and the valid names unless ``task`` is a Meta-World task."""
    if task not in metaworld_tasks():
        raise ValueError(
            f"--env.task: {task!r} is not a Meta-World task; expected a <task>-v3 name, one of "
            f"{', '.join(metaworld_tasks())} (MT10: {', '.join(METAWORLD_MT10)})"
        )


def _metaworld_frame_names(prefix: str) -> tuple[str, ...]:
    objects = (f"{prefix}object{i}.{part}" for i in (1, 2) for part in METAWORLD_OBJECT)
    return (f"{prefix}hand.x", f"{prefix}hand.y", f"{prefix}hand.z", f"{prefix}gripper.opening", *objects)


@EnvConfig.register_subclass("metaworld_state")
@dataclass
class MetaWorldStateEnvConfig(ClassicEnvConfig):
    """One Meta-World task (``--env.task=push-v3``; MT10: ``METAWORLD_MT10``) through LeRobot's own Meta-World env,
    observed as state and never rendered: ``agent_pos`` (hand xyz, gripper opening) → ``observation.state`` and
    Meta-World's 39 values (hand, gripper, two objects, the previous frame's same 18, goal) →
    ``observation.environment_state``. Action: hand motion (×1 cm) and gripper effort, each in [-1, 1]. An episode
    ends at its first success, as in LeRobot's ``metaworld`` env type; object and goal positions come from the
    episode's seed."""

    task: str | None = "push-v3"
    # Share of the play agent's moves (--agent=play) that hold one hand command for 10-40 steps, as the scripted
    # experts hold theirs; 0 is the play of the first Meta-World results (targets and pauses only).
    play_held_moves: float = 0.5
    # Share of play's moves that grasp the first object and carry it to a random point (the goal is never read);
    # 0 is play that reads the hand only.
    play_object_moves: float = 0.0
    STATE_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {
        "agent_pos": ("hand.x", "hand.y", "hand.z", "gripper.opening"),
        "environment_state": (
            *_metaworld_frame_names(""),
            *_metaworld_frame_names("previous."),
            "goal.x",
            "goal.y",
            "goal.z",
        ),  # fmt: skip
    }
    fps: int = 80
    episode_length: int = 500  # Meta-World's own limit
    features: dict[str, PolicyFeature] = field(default_factory=lambda: state_env_features(4, 4, 39))
    features_map: dict[str, str] = field(default_factory=lambda: dict(STATE_ENV_FEATURES_MAP))
    action_names: tuple[str, ...] = ("dx", "dy", "dz", "grasp")

    @property
    def gym_id(self) -> str:
        return f"{GYM_NAMESPACE}/MetaWorldState-v0"

    @property
    def gym_kwargs(self) -> dict:
        return {
            **super().gym_kwargs, "task": self.task, "play_held_moves": self.play_held_moves,
            "play_object_moves": self.play_object_moves,
        }  # fmt: skip

    def validate(self) -> None:
        check_metaworld_task(self.task)
        if not 1 <= self.episode_length <= 500:
            raise ValueError(f"--env.episode_length must be between 1 and Meta-World's 500, got {self.episode_length}")
        if not 0.0 <= self.play_held_moves <= 1.0:
            raise ValueError(f"--env.play_held_moves is a share of play's moves, in [0, 1]; got {self.play_held_moves}")
        if not 0.0 <= self.play_object_moves <= 1.0:
            raise ValueError(
                f"--env.play_object_moves is a share of play's moves, in [0, 1]; got {self.play_object_moves}"
            )

    def settings(self) -> dict:
        settings = {**super().settings(), "task": self.task, "play_held_moves": self.play_held_moves}
        if self.play_object_moves:  # absent at 0: the settings (and data folders) of hand-only play stay as they were
            settings["play_object_moves"] = self.play_object_moves
        return settings
