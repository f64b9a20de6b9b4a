"""A dataset shaped like a real SO-101 teleoperation recording, written by LeRobot's own writer: two cameras (640×480
by default) that show a six-joint arm, ``observation.state`` as the follower's six joint positions in degrees (the
gripper 0 … 100), ``action`` as the leader arm's joint positions, 30 fps, episodes of a few hundred frames.

The follower behaves as a real one measured (``ArmDynamics``; docs/relabelling.md): the leader's position reaches
the servos after a transport delay, each servo then closes a share of the gap per frame (a soft P controller),
gravity holds shoulder_lift and elbow_flex below their targets by a pose-dependent offset, the jaws stop on a grasped
object while the leader keeps closing, and readings are quantised like 12-bit encoders, with noise. The operator
moves, holds and moves again. The cameras draw the arm by its forward kinematics from the front and from above,
over a fixed textured table, so that a codec has real work.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from PIL import Image, ImageDraw

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
CAMERAS = ("observation.images.front", "observation.images.wrist")
# Joint ranges in degrees (gripper: 0 shut … 100 open), the spread of the teleoperator's waypoints.
LOW = np.array([-110.0, -100.0, -90.0, -95.0, -160.0, 0.0], dtype=np.float32)
HIGH = np.array([110.0, 100.0, 90.0, 95.0, 160.0, 100.0], dtype=np.float32)
SENSOR_NOISE = 2.0  # standard deviation, in 0–255 levels
LINKS = (0.12, 0.11, 0.10, 0.06)  # base height, upper arm, forearm, hand (metres)


def arm_features(
    height: int = 480, width: int = 640, video: bool = True, cameras: bool = True, body: ArmBody | None = None
) -> dict:
    """LeRobot features of the recording (as an SO-101 follower records them, or ``body``'s joints);
    ``cameras=False``: joints only."""
    body = body or SO101
    camera = {
        "dtype": "video" if video else "image",
        "shape": (height, width, 3),
        "names": ["height", "width", "channels"],
    }
    state = {"dtype": "float32", "shape": (len(body.state_names),), "names": list(body.state_names)}
    action = {"dtype": "float32", "shape": (len(body.action_names),), "names": list(body.action_names)}
    views = {key: dict(camera) for key in CAMERAS} if cameras else {}
    return {**views, "observation.state": state, "action": action}


def arm_points(q: np.ndarray) -> np.ndarray:
    """3-D points (base, shoulder, elbow, wrist, hand tip, left jaw, right jaw) of joint positions ``q`` (degrees)."""
    pan, lift, elbow, wrist, roll, grip = np.radians(q[:5]).tolist() + [float(q[5]) / 100.0]
    heading = np.array([np.cos(pan), np.sin(pan), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(up, heading)
    points = [np.zeros(3), up * LINKS[0]]
    angle = np.pi / 2 - np.radians(0.0)
    for link, bend in zip(LINKS[1:], (lift, elbow, wrist), strict=True):
        angle -= bend
        points.append(points[-1] + link * (np.cos(angle) * heading + np.sin(angle) * up))
    tip, direction = points[-1], (points[-1] - points[-2]) / LINKS[3]
    normal = np.cos(roll) * side + np.sin(roll) * np.cross(direction, side)
    jaw = 0.01 + 0.03 * grip
    points += [tip + jaw * normal + 0.03 * direction, tip - jaw * normal + 0.03 * direction]
    return np.stack(points)


def _table(height: int, width: int, seed: int) -> Image.Image:
    rng = np.random.default_rng(seed)
    coarse = rng.integers(100, 160, size=(height // 40 + 2, width // 40 + 2, 3), dtype=np.uint8)
    base = (
        Image.fromarray(coarse)
        .resize((width + 80, height + 80), Image.BILINEAR)
        .crop((40, 40, width + 40, height + 40))
    )
    grain = rng.integers(-4, 5, size=(height, width, 1))
    return Image.fromarray(np.clip(np.asarray(base).astype(np.int16) + grain, 0, 255).astype(np.uint8))


def render(q: np.ndarray, background: Image.Image, view: str, noise: np.ndarray | None = None) -> np.ndarray:
    """One camera frame (H, W, 3) uint8 of the arm at ``q``: "front" sees x–z, "wrist" looks down on x–y;
    ``noise`` (H, W, 3) int16 is the sensor's noise of this frame."""
    width, height = background.size
    points = arm_points(q)
    if view == "front":
        scale = 0.85 * height / sum(LINKS)
        pixels = np.stack([width / 2 + scale * points[:, 1], height * 0.92 - scale * points[:, 2]], axis=1)
    else:
        scale = 0.45 * min(width, height) / sum(LINKS[1:])
        pixels = np.stack([width / 2 + scale * points[:, 1], height / 2 - scale * points[:, 0]], axis=1)
    image = background.copy()
    draw = ImageDraw.Draw(image)
    thickness = max(2, width // 60)
    colours = [(40, 40, 40), (230, 120, 20), (230, 120, 20), (30, 90, 200)]
    for i, colour in enumerate(colours):
        draw.line([tuple(pixels[i]), tuple(pixels[i + 1])], fill=colour, width=thickness)
    for jaw in (5, 6):
        draw.line([tuple(pixels[4]), tuple(pixels[jaw])], fill=(200, 30, 30), width=max(1, thickness // 2))
    for p in pixels[:5]:
        r = thickness * 0.8
        draw.ellipse([p[0] - r, p[1] - r, p[0] + r, p[1] + r], fill=(250, 250, 250))
    if noise is None:
        return np.asarray(image)
    return np.clip(np.asarray(image).astype(np.int16) + noise, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class ArmDynamics:
    """How the follower follows the leader. Defaults follow a real SO-101 teleoperation recording (30 fps; the mean
    absolute error between a_t and s_{t+k} is smallest at k = 4 there, and leaves about 1.4° on shoulder_lift, 2.8°
    on elbow_flex and 1.7 on the gripper; docs/relabelling.md)."""

    # Frames between the leader's reading and the follower's servos starting to move towards it. With the default
    # response the follower is then closest to a_t at s_{t+delay+2}: the default 2 gives the real arm's 4 frames.
    delay: int = 2
    # Share of the remaining gap a servo closes per frame (a first-order response; 1 = at once).
    response: float = 0.6
    # A servo does not move while its error is below this (degrees; stiction and the servo's dead band).
    dead_band: float = 0.3
    # Degrees by which gravity holds shoulder_lift and elbow_flex below their targets, at the pose of greatest load.
    gravity: tuple[float, float] = (2.5, 4.0)
    # Degrees by which gravity holds wrist_flex below its target at most, by the whole arm's pose (the upper arm's,
    # the forearm's and the hand's angles): a follower joint whose error only the other joints' windows explain.
    wrist_gravity: float = 0.0
    # Probability that a closing of the gripper grasps an object, which stops the jaws at its width.
    grasp_probability: float = 0.5
    # Encoder resolution: 4096 steps per turn (degrees), the gripper's 0 … 100 spanning about a third of a turn.
    quantise: bool = True
    # Standard deviation of a reading's noise before quantisation (degrees; gripper units).
    reading_noise: float = 0.05
    # The operator's hand trembles by this much (degrees per frame of a random walk, pulled back to the path).
    tremor: float = 0.3

    def __post_init__(self):
        if self.delay < 0 or not 0.0 < self.response <= 1.0:
            raise ValueError(f"delay must be ≥ 0 frames and response in (0, 1], got {self.delay}, {self.response}")


ENCODER_STEP = np.array([360.0 / 4096] * 5 + [100.0 / 1365], dtype=np.float64)


def gravity_offset(q: np.ndarray, gravity: tuple[float, float], wrist: float = 0.0) -> np.ndarray:
    """How far below its command gravity holds each joint at ``q`` (degrees): the load on shoulder_lift grows with
    how far out the upper arm and forearm reach, on elbow_flex with the forearm's reach alone, on wrist_flex with the
    hand's angle over the whole arm."""
    lift, elbow = np.radians(q[1]), np.radians(q[1] + q[2])
    offset = np.zeros(len(JOINTS))
    offset[1] = -gravity[0] * (0.6 * np.cos(lift) + 0.4 * np.cos(elbow))
    offset[2] = -gravity[1] * np.cos(elbow)
    offset[3] = -wrist * np.cos(np.radians(q[1] + q[2] + q[3]))
    return offset


def operator_targets(
    frames: int,
    rng: np.random.Generator,
    tremor: float,
    grasp_probability: float,
    low: np.ndarray = LOW,
    high: np.ndarray = HIGH,
    gripper: int | None = 5,
    idle: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The leader's joint positions (frames, joints): glides between random waypoints in ``low`` … ``high`` over 15–50
    frames, each followed by a hold of 0–45 frames, all with a trembling hand; and where a grasped object stops the
    jaws (frames,): its width while it is held, −inf elsewhere. A glide that closes the ``gripper`` grasps with
    ``grasp_probability``: the operator then shuts the leader's jaws (0–5 % of its range) on an object 10–40 % wide.
    Joints marked ``idle`` rest near the middle of their range, the hand's tremor alone moving them."""
    joints = len(low)
    span_of = high - low
    targets = np.empty((frames, joints), dtype=np.float64)
    stops = np.full(frames, -np.inf)
    current = rng.uniform(low * 0.5, high * 0.5)
    idle = np.zeros(joints, dtype=bool) if idle is None else np.asarray(idle, dtype=bool)
    if idle.any():  # an idle joint rests near the middle of its range, a little apart from one episode to the next
        current = np.where(idle, (low + high) / 2 + rng.uniform(-0.03, 0.03, joints) * span_of, current)
    t = 0
    while t < frames:
        span, hold = int(rng.integers(15, 51)), int(rng.integers(0, 46))
        goal = np.where(idle, current, rng.uniform(low, high))
        grasp = gripper is not None and goal[gripper] < current[gripper] and rng.random() < grasp_probability
        if grasp:
            goal[gripper] = low[gripper] + rng.uniform(0.0, 0.05) * span_of[gripper]
        ease = (1 - np.cos(np.linspace(0, np.pi, span))) / 2
        targets[t : t + span] = (current + ease[:, None] * (goal - current))[: frames - t]
        targets[t + span : t + span + hold] = goal
        if grasp:
            width = low[gripper] + rng.uniform(0.1, 0.4) * span_of[gripper]
            stops[t : t + span + hold] = min(width, current[gripper])
        current, t = goal, t + span + hold
    shake = np.zeros(joints)
    for t in range(frames):  # a random walk pulled back to the path: the hand never quite rests
        shake = 0.9 * shake + rng.normal(0.0, tremor, joints)
        targets[t] += shake
    return targets, stops


@dataclass(frozen=True)
class ArmBody:
    """Which arms record: the leader's joints (the action's names), the follower's (``observation.state``'s) and how a
    leader pose becomes the follower's command, ``command = mapping @ leader + offset`` (identity and 0 by default).
    Per follower joint: frames of delay beyond ``ArmDynamics.delay``, multipliers of its response and dead band.
    ``unit`` scales the hand's tremor, noises and dead bands (1: degrees; π/180: radians)."""

    name: str
    action_names: tuple[str, ...]
    state_names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    gripper: int | None = None  # the leader's gripper column (its closings may grasp)
    follower_gripper: int | None = None  # the follower column that a grasped object stops
    mapping: tuple[tuple[float, ...], ...] | None = None
    offset: tuple[float, ...] | None = None
    extra_delay: tuple[int, ...] | None = None
    response: tuple[float, ...] | None = None
    dead_band: tuple[float, ...] | None = None
    unit: float = 1.0
    encoder_step: tuple[float, ...] | None = None
    gravity: bool = False  # SO-101 gravity on shoulder_lift and elbow_flex (``gravity_offset``)
    robot_type: str = "so101_follower"

    def per_joint(self, values: tuple | None, default: float) -> np.ndarray:
        return np.full(len(self.state_names), default) if values is None else np.asarray(values, dtype=np.float64)

    def commands(self, leader: np.ndarray) -> np.ndarray:
        """The follower's commands (frames, state joints) for leader poses (frames, action joints)."""
        mapped = leader if self.mapping is None else leader @ np.asarray(self.mapping, dtype=np.float64).T
        return mapped + self.per_joint(self.offset, 0.0)


SO101 = ArmBody(
    "so101", tuple(f"{j}.pos" for j in JOINTS), tuple(f"{j}.pos" for j in JOINTS), tuple(LOW), tuple(HIGH),
    gripper=5, follower_gripper=5, encoder_step=tuple(ENCODER_STEP), gravity=True,
)  # fmt: skip
# A second SO-101 whose leader's wrist_roll reads 74 above the follower's, and whose follower's wrist_roll barely
# follows (it is driven over a twelfth of the leader's travel, slowly, through a wide dead band: its state spans a
# few units while the leader's spans tens), as measured on a real recording.
SO101_MISCALIBRATED = replace(
    SO101, name="so101_miscalibrated", offset=(0, 0, 0, 0, -74.0, 0),
    mapping=tuple(tuple(float(i == j) * (1 / 12 if i == 4 else 1) for j in range(6)) for i in range(6)),
    response=(1, 1, 1, 1, 0.2, 1), dead_band=(1, 1, 1, 1, 6.0, 1),
)  # fmt: skip
# An SO-101 leader driving another follower of seven values (an AgileX Piper's joint_1 … joint_6 and gripper): signs,
# scales, offsets and one coupling differ from the identity, joint_4 has no leader joint and stays near 0.
OTHER_LEADER = ArmBody(
    "other_leader", tuple(f"{j}.pos" for j in JOINTS), tuple(f"joint_{i}.pos" for i in range(1, 7)) + ("gripper.pos",),
    tuple(LOW), tuple(HIGH), gripper=5, follower_gripper=6,
    mapping=(
        (-1.0, 0, 0, 0, 0, 0), (0, 0.8, 0.15, 0, 0, 0), (0, 0, -1.1, 0, 0, 0), (0, 0, 0, 0, 0, 0),
        (0, 0, 0, 0.9, 0, 0), (0, 0, 0, 0, 1.0, 0), (0, 0, 0, 0, 0, 0.7),
    ),
    offset=(5.0, -10.0, 20.0, 0.0, 3.0, -8.0, 0.0), encoder_step=(0.001,) * 7, robot_type="piper_follower",
)  # fmt: skip
HUMANOID_ARM = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch", "wrist_yaw")
HUMANOID_HAND = ("thumb_rotation", "thumb_bend", "index", "middle", "ring", "little")
HUMANOID_NAMES = tuple(
    f"{side}_{joint}" for part in (HUMANOID_ARM, HUMANOID_HAND) for side in ("left", "right") for joint in part
)
HUMANOID_LEFT_ARM = tuple(f"left_{joint}" for joint in HUMANOID_ARM)
_is_hand = np.array([name.split("_", 1)[1] in HUMANOID_HAND for name in HUMANOID_NAMES])
# A humanoid's two 7-joint arms and two 6-joint hands in radians, names without ".pos": the fingers answer later
# (5 more frames of delay) and slower than the arms, as the real recording's copy lags show (4–7 arms, 9–10 fingers).
HUMANOID = ArmBody(
    "humanoid", HUMANOID_NAMES, HUMANOID_NAMES,
    tuple(np.where(_is_hand, 0.0, -1.5).tolist()), tuple(np.where(_is_hand, 1.7, 1.5).tolist()),
    extra_delay=tuple(np.where(_is_hand, 5, 0).tolist()), response=tuple(np.where(_is_hand, 0.7, 1.0).tolist()),
    unit=np.pi / 180, encoder_step=(2 * np.pi / 4096,) * 26, robot_type="humanoid",
)  # fmt: skip


def teleoperated_episode(
    frames: int,
    rng: np.random.Generator,
    dynamics: ArmDynamics = ArmDynamics(),
    body: ArmBody = SO101,
    idle: tuple[str, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """The follower's joint readings (frames, state joints) and the leader's positions (frames, action joints),
    float32 (``ArmDynamics``, ``ArmBody``); the leader joints named in ``idle`` stay put but for the hand's tremor."""
    unit = body.unit
    idle_mask = np.isin(body.action_names, idle)
    targets, stops = operator_targets(
        frames, rng, dynamics.tremor * unit, dynamics.grasp_probability, np.asarray(body.low),
        np.asarray(body.high), body.gripper, idle_mask,
    )  # fmt: skip
    commands = body.commands(targets)
    joints = commands.shape[1]
    delays = dynamics.delay + body.per_joint(body.extra_delay, 0).astype(np.int64)
    response = np.clip(dynamics.response * body.per_joint(body.response, 1.0), 0.0, 1.0)
    dead_band = dynamics.dead_band * unit * body.per_joint(body.dead_band, 1.0)
    grip = body.follower_gripper
    if grip is not None:  # the object's width in the follower's units
        scale = 1.0 if body.mapping is None else body.mapping[grip][body.gripper]
        stops = scale * stops + body.per_joint(body.offset, 0.0)[grip]
    q = commands[0] + rng.normal(0, 2.0 * unit, joints)
    positions = np.empty_like(commands)
    columns = np.arange(joints)
    for t in range(frames):
        positions[t] = q
        command = commands[np.maximum(t - delays, 0), columns]
        error = (
            command + gravity_offset(q, dynamics.gravity, dynamics.wrist_gravity) - q if body.gravity else command - q
        )
        q = q + response * np.where(np.abs(error) > dead_band, error, 0.0)
        if grip is not None:  # the object, as long as the delayed command holds it
            q[grip] = max(q[grip], stops[min(max(t + 1 - delays[grip], 0), frames - 1)])
    readings = positions + rng.normal(0.0, dynamics.reading_noise * unit, positions.shape)
    if dynamics.quantise and body.encoder_step is not None:
        step = np.asarray(body.encoder_step)
        readings = np.round(readings / step) * step
    return readings.astype(np.float32), targets.astype(np.float32)
