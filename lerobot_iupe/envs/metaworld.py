"""One Meta-World task through LeRobot's own ``metaworld`` env, observed as state and never rendered.

LeRobot's ``MetaworldEnv`` renders a 480×480 camera at every step (about 0.25 s on a CPU) and exposes only the first
4 of Meta-World's 39 observation values (its ``obs_type="state"`` raises). This subclass keeps LeRobot's task set-up,
seeding (``reset(seed)`` draws the object and goal positions), success (``info["is_success"]``, the episode ending at
its first success) and scripted expert, and returns ``agent_pos`` (hand xyz, gripper opening) and the 39 values as
``environment_state``. It carries the expert (Meta-World's ``Sawyer<Task>V3Policy`` fed the 39 values) and a
goal-agnostic play agent for pre-demonstrations, as the package's other envs do.
"""

from __future__ import annotations

import os
import threading
import warnings

if not os.environ.get("DISPLAY"):  # MuJoCo picks its OpenGL backend when first imported: offscreen EGL headless
    os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np  # noqa: E402
from gymnasium import spaces  # noqa: E402
from lerobot.envs.metaworld import MetaworldEnv  # noqa: E402

from lerobot_iupe.envs.metaworld_config import check_metaworld_task  # noqa: E402

OBSERVATION_SIZE = 39
# Where play moves the hand: Meta-World's hand range (metaworld.sawyer_xyz_env's default hand_low / hand_high,
# widened to the tasks' object and goal positions, from near the table to well above it).
PLAY_LOW, PLAY_HIGH = np.array([-0.3, 0.4, 0.05]), np.array([0.3, 0.9, 0.3])
PLAY_MAX_STEPS_PER_TARGET = 40
PLAY_PAUSE = (0.2, (5, 15))  # chance that the next move is a pause where the hand is, and the pause's steps
PLAY_GRASP_HOLD = (5, 30)  # steps a gripper command is held
# A held move: one hand command kept for 10-40 steps, each axis at a bound (±1) or uniform in between. The scripted
# experts saturate their commands for tens of steps, so the mocap target runs ahead of the lagging hand; moves that
# steer toward a target never do that, and an IDM trained on them alone labels the expert's approach short
# (button-press-topdown's y: R² -0.99 without held moves, 0.43 with half of them; benchmarks/cycle_play.md).
PLAY_HELD_STEPS = (10, 40)
# An object move (share ``play_object_moves``): over the first object, down to it, the gripper closed on it for 8-15
# steps, then carried closed to a random point. A hand-only play never closes the fingers on an object, so an IDM
# trained on it cannot tell a grasp that holds a puck from none (pick-place's grasp R² below 0; trailing_tasks.md).
PLAY_OBJECT_ABOVE, PLAY_OBJECT_LOW = 0.1, (0.0, 0.04)
PLAY_OBJECT_CLOSE_STEPS = (8, 15)
# Meta-World draws its task list from NumPy's global generator (seeding it, then restoring it): two threads building
# envs at once drew interleaved values ("Only generated 49 unique goals, not 50").
_BUILDING = threading.Lock()
# The sketch render() draws: the table's x (left-right) and y (away from the robot) in metres, and its pixels.
SKETCH_LOW, SKETCH_HIGH, SKETCH_SIZE = np.array([-0.5, 0.3]), np.array([0.5, 1.0]), 96


class MetaWorldStateEnv(MetaworldEnv):
    """LeRobot's Meta-World env for one task (``push-v3``, …) with a state observation: ``agent_pos`` (4) and
    ``environment_state`` (Meta-World's 39 values: hand, gripper, two objects' position and quaternion, the same
    18 of the previous frame, goal). Nothing is rendered."""

    def __init__(self, task: str = "push-v3", play_held_moves: float = 0.5, play_object_moves: float = 0.0):
        check_metaworld_task(task)  # LeRobot's class raises a bare KeyError
        self.play_held_moves, self.play_object_moves = play_held_moves, play_object_moves
        # LeRobot's class refuses obs_type="state" and renders for the pixel types: its pixel type is named here
        # only to construct it, and _format_raw_obs below never renders.
        super().__init__(task=task, obs_type="pixels_agent_pos")
        self.render_mode = None
        self.observation_space = spaces.Dict(
            {
                "agent_pos": spaces.Box(-np.inf, np.inf, (4,), dtype=np.float32),
                "environment_state": spaces.Box(-np.inf, np.inf, (OBSERVATION_SIZE,), dtype=np.float32),
            }
        )
        self._observation = np.zeros(OBSERVATION_SIZE)
        self._play: dict = {}

    def _ensure_env(self) -> None:
        with _BUILDING:
            super()._ensure_env()

    def _format_raw_obs(self, raw_obs: np.ndarray) -> dict[str, np.ndarray]:
        self._observation = np.asarray(raw_obs, dtype=np.float64)
        return {
            "agent_pos": self._observation[:4].astype(np.float32),
            "environment_state": self._observation.astype(np.float32),
        }

    def reset(self, seed: int | None = None, **kwargs) -> tuple[dict, dict]:
        self._play = {}
        observation, info = super().reset(seed=seed, **kwargs)
        return observation, {**info, "task": self.task}

    def render(self) -> np.ndarray:
        """A top-down sketch of the table drawn from the state (no MuJoCo rendering: lerobot-eval's videos stay cheap
        and work where OpenGL cannot): goal green, first object red, hand blue (paler as the gripper opens)."""
        frame = np.full((SKETCH_SIZE, SKETCH_SIZE, 3), 235, dtype=np.uint8)
        observation = self._observation
        marks = [(observation[36:39], (40, 170, 40)), (observation[4:7], (200, 40, 40))]
        opening = float(np.clip(observation[3], 0.0, 1.0))
        marks.append((observation[:3], (int(40 + 150 * opening), int(40 + 150 * opening), 220)))
        for position, colour in marks:
            column, row = ((position[:2] - SKETCH_LOW) / (SKETCH_HIGH - SKETCH_LOW) * SKETCH_SIZE).astype(int)
            row = SKETCH_SIZE - 1 - row  # y grows away from the robot: up in the picture
            frame[max(row - 3, 0) : row + 4, max(column - 3, 0) : column + 4] = colour
        return frame

    def expert_action(self) -> np.ndarray:
        """Meta-World's scripted policy for this task on the current 39 values, clipped to the action space as
        the env clips it (its proportional gains overshoot ±1, with a warning at every step)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            action = self.expert_policy.get_action(self._observation)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def play_action(self) -> np.ndarray:
        """Goal-agnostic play: a share ``play_object_moves`` of the moves grasp the first object and carry it to a
        random point; a share ``play_held_moves`` of the others hold one random hand command for 10-40 steps; the
        rest travel to random targets in the working box at a random speed, or pause where the hand is. Outside an
        object move the gripper is opened or closed at random and held for 5-30 steps. It never reads the goal, and
        reads the objects only in object moves."""
        rng, play, hand = self.np_random, self._play, self._observation[:3]
        if play.get("legs"):
            return self._object_leg_action(rng, play, hand)
        moving = play.get("speed", 0.0) > 0
        reached = moving and np.linalg.norm(play["target"] - hand) < 0.01
        if not play or play["steps"] >= play["max_steps"] or reached:
            if self.play_object_moves and rng.random() < self.play_object_moves:
                play.update(legs=self._object_legs(rng), held=None, speed=0.0, steps=0, max_steps=0)
                play.setdefault("grasp", -1.0)
                return self._object_leg_action(rng, play, hand)
            if self.play_held_moves and rng.random() < self.play_held_moves:
                at_bound = rng.random(3) < 0.5
                command = np.where(at_bound, rng.choice([-1.0, 1.0], 3), rng.uniform(-1.0, 1.0, 3))
                steps = int(rng.integers(*PLAY_HELD_STEPS, endpoint=True))
                play.update(held=command, speed=0.0, steps=0, max_steps=steps)
            elif rng.random() < PLAY_PAUSE[0]:
                steps = int(rng.integers(*PLAY_PAUSE[1]))
                play.update(held=None, target=hand.copy(), speed=0.0, steps=0, max_steps=steps)
            else:
                target, speed = rng.uniform(PLAY_LOW, PLAY_HIGH), rng.uniform(0.3, 1.0)
                play.update(held=None, target=target, speed=speed, steps=0, max_steps=PLAY_MAX_STEPS_PER_TARGET)
            play.setdefault("grasp", -1.0)
            play.setdefault("hold", 0)
        if play["hold"] <= 0:
            play["grasp"] = float(rng.choice([-1.0, 1.0])) if rng.random() < 0.8 else float(rng.uniform(-1, 1))
            play["hold"] = int(rng.integers(*PLAY_GRASP_HOLD, endpoint=True))
        play["steps"] += 1
        play["hold"] -= 1
        if play["held"] is not None:
            move = np.clip(play["held"] + rng.normal(0.0, 0.1, 3), -1.0, 1.0)
        else:
            move = np.clip(10.0 * (play["target"] - hand), -1.0, 1.0) * play["speed"]  # the experts' gain, p=10
            move = np.clip(move + rng.normal(0.0, 0.1 if play["speed"] else 0.02, 3), -1.0, 1.0)
        return np.asarray([*move, play["grasp"]], dtype=np.float32)

    def _object_legs(self, rng: np.random.Generator) -> list[dict]:
        """An object move's legs, each a target the hand steers to (until reached, or for a fixed time) and the
        gripper command held meanwhile."""
        obj = self._observation[4:7]
        above = obj + np.array([*rng.uniform(-0.01, 0.01, 2), PLAY_OBJECT_ABOVE])
        low = obj + np.array([*rng.uniform(-0.005, 0.005, 2), rng.uniform(*PLAY_OBJECT_LOW)])
        close_steps = int(rng.integers(*PLAY_OBJECT_CLOSE_STEPS, endpoint=True))
        carry_to, carry_speed = rng.uniform(PLAY_LOW, PLAY_HIGH), float(rng.uniform(0.3, 1.0))
        steps = PLAY_MAX_STEPS_PER_TARGET
        return [
            _leg(above, grasp=-1.0, speed=1.0, max_steps=steps, until_reached=True),
            _leg(low, grasp=-1.0, speed=0.5, max_steps=steps, until_reached=True),
            _leg(low, grasp=1.0, speed=0.5, max_steps=close_steps, until_reached=False),
            _leg(carry_to, grasp=1.0, speed=carry_speed, max_steps=steps, until_reached=True),
        ]

    def _object_leg_action(self, rng: np.random.Generator, play: dict, hand: np.ndarray) -> np.ndarray:
        """The current leg's step (the experts' gain, p = 10); after the last leg the next call chooses a new move
        and a new gripper command."""
        legs = play["legs"]
        leg = legs[0]
        move = np.clip(10.0 * (leg["target"] - hand), -1.0, 1.0) * leg["speed"]
        move = np.clip(move + rng.normal(0.0, 0.02, 3), -1.0, 1.0)
        leg["max_steps"] -= 1
        if leg["max_steps"] <= 0 or (leg["until_reached"] and np.linalg.norm(leg["target"] - hand) < 0.01):
            legs.pop(0)
        if not legs:
            play.update(steps=0, max_steps=0, hold=0)
        return np.asarray([*move, leg["grasp"]], dtype=np.float32)


def _leg(target: np.ndarray, grasp: float, speed: float, max_steps: int, until_reached: bool) -> dict:
    return {"target": target, "grasp": grasp, "speed": speed, "max_steps": max_steps, "until_reached": until_reached}
