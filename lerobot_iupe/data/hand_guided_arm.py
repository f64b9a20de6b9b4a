"""A six-joint arm moved by hand (drag mode), as a real industrial arm records it (docs/relabelling.md): 10 fps
whose real time steps vary while the timestamps do not, measured joint velocities as the action, and a gripper
commanded from a keyboard whose opening no state column records, seen by a camera on the hand."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw

from lerobot_iupe.data.arm_recording import ArmBody, operator_targets

# A six-joint arm moved by hand (drag mode) at 10 fps, as a real industrial arm records it: the state its joint
# positions in radians, the action their *measured velocities* in rad/s and a gripper commanded from a keyboard
# (0 open, 1 closed) whose opening no state column records (``hand_guided_episode``). Its cameras draw it with the
# SO-101's links (joint_5 turns the hand about its axis with joint_4), so that only they show the jaws.
VELOCITY_JOINTS = tuple(f"joint_{i}" for i in range(6))
VELOCITY_ARM = ArmBody(
    "velocity_arm", tuple(f"{j}_vel" for j in VELOCITY_JOINTS) + ("gripper",), VELOCITY_JOINTS,
    (-1.8, -1.5, -1.4, -1.5, -2.5, -1.0), (1.8, 1.5, 1.4, 1.5, 2.5, 1.0), unit=np.pi / 180,
    robot_type="hand_guided_arm",
)  # fmt: skip
# Per joint, how far the measured velocity runs behind (+) or ahead (−) of the motion: the real arm's velocities best
# match the frame difference s_{t+k+1} − s_{t+k} at k = −1, 0 or 1 depending on the joint.
VELOCITY_READING_DELAY_S = (0.0, 0.05, -0.05, 0.1, 0.0, -0.1)
FINE_RATE = 200  # Hz of the continuous motion that the irregular frames sample


def hand_guided_episode(
    frames: int, rng: np.random.Generator, fps: int = 10, idle: tuple[str, ...] = ()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joint positions (frames, 6) rad, actions (frames, 7): measured joint velocities rad/s and the keyboard
    gripper, the jaws' opening (frames,) 0 shut … 1 open) of ``VELOCITY_ARM`` moved by hand. The real time between
    frames varies from 0.05 to 0.35 s while the recording's timestamps say 1/``fps`` (as the real recording's tools
    regularise them); each velocity is read with its joint's ``VELOCITY_READING_DELAY_S``, with noise. The key
    toggles the gripper every 1–6 s; the jaws follow it with a 0.3 s time constant. Joints named in ``idle`` (their
    velocity names or joint names) rest but for the hand's tremor."""
    body = VELOCITY_ARM
    steps = np.clip(rng.normal(1.0 / fps, 0.06, frames), 0.05, 0.35)
    times = np.r_[0.0, np.cumsum(steps)[:-1]] + 0.2
    fine = int(np.ceil((times[-1] + 0.5) * FINE_RATE)) + 1
    names = set(idle) | {f"{j}_vel" for j in idle}
    idle_mask = np.isin(body.action_names[:6], list(names)) | np.isin(body.state_names, list(names))
    # The operator's glides, on the fine clock: one waypoint every 1.5–5 s rather than every 15–50 frames.
    waypoints, _ = operator_targets(
        int(np.ceil(fine / 20)) + 60, rng, 0.05 * body.unit, 0.0, np.asarray(body.low[:6]), np.asarray(body.high[:6]),
        None, idle_mask,
    )  # fmt: skip
    clock = np.arange(fine) / FINE_RATE
    path = np.stack([np.interp(clock, np.arange(len(waypoints)) / 10.0, w) for w in waypoints.T], axis=1)
    rate = np.gradient(path, 1.0 / FINE_RATE, axis=0)
    positions = np.stack([np.interp(times, clock, p) for p in path.T], axis=1)
    read_at = times[:, None] - np.asarray(VELOCITY_READING_DELAY_S)[None, :]
    velocities = np.stack([np.interp(read_at[:, j], clock, rate[:, j]) for j in range(6)], axis=1)
    velocities += rng.normal(0.0, 0.005, velocities.shape)
    key, closed, t = np.zeros(frames), 0.0, 0.0
    toggles = []
    while t < times[-1]:
        t += rng.uniform(1.0, 6.0)
        toggles.append(t)
    for toggle in toggles:
        closed = 1.0 - closed
        key[times >= toggle] = closed
    opening, jaw = np.empty(frames), 1.0 - key[0]
    for i in range(frames):
        opening[i] = jaw
        jaw += (1.0 - key[i] - jaw) * (1.0 - np.exp(-steps[i] / 0.3))
    readings = positions + rng.normal(0.0, 0.0005, positions.shape)
    actions = np.concatenate([velocities, key[:, None]], axis=1)
    return readings.astype(np.float32), actions.astype(np.float32), opening.astype(np.float32)


def wrist_view(joints: np.ndarray, opening: float, background: Image.Image, noise: np.ndarray | None) -> np.ndarray:
    """What a camera on the velocity arm's hand sees (H, W, 3) uint8: the table, shifted and turned as the joints
    move, and the gripper's two jaws rising from the bottom of the image, apart by their ``opening`` (0 … 1)."""
    width, height = background.size
    shift = (int(0.25 * width * np.sin(joints[0])), int(0.25 * height * np.sin(joints[1] + joints[2])))
    image = background.rotate(float(np.degrees(joints[4] + joints[5])), translate=shift, fillcolor=(90, 90, 90))
    draw = ImageDraw.Draw(image)
    jaw_width, gap = 0.12 * width, (0.06 + 0.16 * float(opening)) * width
    for side in (-1, 1):
        inner = width / 2 + side * gap
        outer = inner + side * jaw_width
        draw.rectangle([min(inner, outer), 0.62 * height, max(inner, outer), height], fill=(45, 45, 50))
    if noise is None:
        return np.asarray(image)
    return np.clip(np.asarray(image).astype(np.int16) + noise, 0, 255).astype(np.uint8)


def drawn_pose(joints: np.ndarray, opening: float) -> np.ndarray:
    """The pose ``render`` draws (SO-101 links, degrees, gripper 0 … 100) of the velocity arm's joints (rad)."""
    degrees = np.degrees(joints)
    return np.array([*degrees[:4], degrees[4] + degrees[5], 100.0 * opening])
