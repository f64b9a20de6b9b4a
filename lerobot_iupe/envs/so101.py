"""The SO-101 pick-and-place task of the ``lerobot_env_so101`` plugin, with its success where LeRobot reads it.

The plugin's env reports success as ``info["succeed"]``; LeRobot's evaluation reads ``info["is_success"]`` and so
scores it 0%. This wrapper adds ``is_success`` (and a task description) around the unmodified plugin env, and
carries the plugin's scripted pick-and-place controller as the expert (it keeps a phase across steps, so it lives
with the env and restarts on every reset) and a goal-agnostic play agent for pre-demonstrations.
"""

from __future__ import annotations

import os

if not os.environ.get("DISPLAY"):  # MuJoCo picks its OpenGL backend when first imported: offscreen EGL headless
    os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
from lerobot_env_so101.mujoco_env import GymRenderingSpec  # noqa: E402
from lerobot_env_so101.pick_place_env import SO101PickPlaceGymEnv  # noqa: E402
from lerobot_env_so101.scripted.pick_place import PickPlaceController  # noqa: E402

# Where play reaches: the box in which the plugin places blocks and goals (x 0.15-0.30 m, y ±0.10 m), widened by
# 3 cm, from grasping height (grasp point 3.5 cm above the table, where jaws close on a block) to 15 cm above it.
# Geometry of the scene, not of any episode. Lower targets pressed the arm into the table: commands without motion.
PLAY_LOW, PLAY_HIGH = np.array([0.12, -0.13, 0.035]), np.array([0.33, 0.13, 0.15])
PLAY_MAX_STEPS_PER_TARGET = 30
PLAY_PAUSE = (0.3, (5, 15))  # chance that the next move is a pause where the arm is, and the pause's steps
PLAY_GRASP_HOLD = (5, 25)  # steps a gripper command is held, like the expert's 8-10-step closing and opening


def use_offscreen_gl() -> None:
    """Render through EGL on a headless machine even when MuJoCo was imported before this module could set
    MUJOCO_GL (LeRobot imports lerobot_env_* plugins first): MuJoCo then picked GLFW, which needs a display. By hand
    because MuJoCo chooses its backend once, at import; its renderer reads the choice from ``gl_context``."""
    from mujoco.rendering.classic import gl_context

    glfw = getattr(gl_context, "GLContext", None) is not None and gl_context.GLContext.__module__.startswith(
        "mujoco.glfw"
    )
    if glfw and not os.environ.get("DISPLAY") and os.environ.get("MUJOCO_GL") == "egl":
        from mujoco.egl import GLContext

        gl_context.GLContext = GLContext


class SO101PickPlaceEnv(gym.Wrapper):
    """``lerobot_env_so101``'s SO101PickPlace env with ``info["is_success"]`` (from its ``succeed``)."""

    task_description = "Pick up the cube and place it on the goal."

    def __init__(self, action_scale: float = 0.025, random_block_position: bool = True, image_obs: bool = False,
                 image_size: int = 64, render_mode: str = "rgb_array", relative_positions: bool = False):  # fmt: skip
        super().__init__(
            SO101PickPlaceGymEnv(
                action_scale=action_scale,
                random_block_position=random_block_position,
                image_obs=image_obs,
                render_mode=render_mode,
                render_spec=GymRenderingSpec(height=image_size, width=image_size),
            )
        )
        # Every SO-101 env renders (the camera observation, or lerobot-eval's videos), so every one renders offscreen
        # headless, without multisampling and shadows: 8x faster on a CPU (benchmarks/measure/render.py), legible at
        # 64 px.
        use_offscreen_gl()
        model = self.env.unwrapped._model
        model.vis.quality.offsamples = 0
        model.vis.quality.shadowsize = 0
        model.light_castshadow[:] = 0
        self.image_obs = image_obs
        self.relative_positions = relative_positions
        if relative_positions:  # block − ee and goal − ee after the block and goal (SO101PickPlaceEnvConfig)
            self.observation_space = gym.spaces.Dict(
                {**self.env.observation_space, "environment_state": gym.spaces.Box(-np.inf, np.inf, (12,), np.float32)}
            )
        self.task = "so101_pickplace"
        self._controller = PickPlaceController(action_scale=action_scale)
        self._action_scale = action_scale
        self._success = False
        self._play: dict = {}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        try:
            obs, info = self.env.reset(seed=seed)
        except Exception as error:  # MuJoCo's renderer raises several types when OpenGL is missing
            if not self.image_obs:
                raise
            raise RuntimeError(
                f"the SO-101 camera (--env.image_obs=true) could not be rendered ({type(error).__name__}: {error}); "
                "it needs offscreen OpenGL: on Debian/Ubuntu `apt-get install libegl1 libgl1-mesa-dri` (make "
                "install does it) with MUJOCO_GL=egl, or MUJOCO_GL=osmesa with libosmesa6"
            ) from error
        self._controller.reset()
        self._play = {}
        self._success = False
        info["is_success"] = False
        return self._observation(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float32).reshape(-1))
        self._success |= bool(info.get("succeed", False))
        info["is_success"] = self._success
        return self._observation(obs), reward, terminated, truncated, info

    def _observation(self, obs: dict) -> dict:
        if not self.relative_positions:
            return obs
        world, ee = obs["environment_state"], obs["agent_pos"][-3:]  # agent_pos ends with the end effector's x, y, z
        relative = np.concatenate([world, world[:3] - ee, world[3:6] - ee]).astype(np.float32)
        return {**obs, "environment_state": relative}

    def expert_action(self) -> np.ndarray:
        """The plugin's scripted controller (hover, descend, close, lift, traverse, lower, open, retreat)."""
        env = self.env.unwrapped
        block = env.data.sensor("block_pos").data
        return self._controller.act(env.ik_point_pos, block, env.goal_pos)

    def play_action(self) -> np.ndarray:
        """Goal-agnostic play, for pre-demonstrations that cover where the expert goes: the grasp point travels to
        random targets in the table's working box at a random speed or pauses where it is, and the gripper is
        opened or closed at random and held for 5-25 steps. It reads the arm's own grasp point only, never the block
        or the goal (uniformly random actions jitter the arm around its start: an IDM trained on them scored R² < 0
        on the expert)."""
        env, rng, play = self.env.unwrapped, self.env.unwrapped.np_random, self._play
        grasp_point = np.asarray(env.ik_point_pos, dtype=np.float64)
        moving = play.get("speed", 0.0) > 0
        reached = moving and np.linalg.norm(play["target"] - grasp_point) < 0.01
        if not play or play["steps"] >= play["max_steps"] or reached:
            if rng.random() < PLAY_PAUSE[0]:  # stay (as the expert does while its gripper closes or opens)
                play.update(target=grasp_point, speed=0.0, steps=0, max_steps=int(rng.integers(*PLAY_PAUSE[1])))
            else:
                target, speed = rng.uniform(PLAY_LOW, PLAY_HIGH), rng.uniform(0.3, 1.0)
                play.update(target=target, speed=speed, steps=0, max_steps=PLAY_MAX_STEPS_PER_TARGET)
            play.setdefault("grasp", 1.0)
            play.setdefault("hold", 0)
        if play["hold"] <= 0:
            play["grasp"] = float(rng.integers(2)) if rng.random() < 0.8 else float(rng.uniform())
            play["hold"] = int(rng.integers(*PLAY_GRASP_HOLD, endpoint=True))
        play["steps"] += 1
        play["hold"] -= 1
        move = np.clip((play["target"] - grasp_point) / self._action_scale, -1.0, 1.0) * play["speed"]
        move = np.clip(move + rng.normal(0.0, 0.1 if play["speed"] else 0.02, 3), -1.0, 1.0)
        return np.asarray([*move, play["grasp"]], dtype=np.float32)
