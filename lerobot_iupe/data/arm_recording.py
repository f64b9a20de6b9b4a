"""A dataset shaped like a real SO-101 recording, written by LeRobot's own writer: two cameras (640×480 by default)
that show a six-joint arm, ``observation.state`` as six joint positions in degrees, ``action`` as the leader arm's
absolute joint targets, 30 fps, episodes of a few hundred frames.

The follower tracks its target with a first-order lag (q_{t+1} = q_t + LAG · (a_t − q_t)), as a position-controlled
servo does, so a_t = q_t + (q_{t+1} − q_t) / LAG: an inverse dynamics model can recover every action from two
frames. The targets move smoothly between random waypoints, like a teleoperator's hand. The cameras draw the arm by
its forward kinematics from the front and from above, over a fixed textured table, so that a codec has real work.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

JOINTS = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
CAMERAS = ("observation.images.front", "observation.images.wrist")
LAG = 0.5
# Joint ranges in degrees (gripper: 0 shut … 100 open), the spread of the teleoperator's waypoints.
LOW = np.array([-110.0, -100.0, -90.0, -95.0, -160.0, 0.0], dtype=np.float32)
HIGH = np.array([110.0, 100.0, 90.0, 95.0, 160.0, 100.0], dtype=np.float32)
SENSOR_NOISE = 2.0  # standard deviation, in 0–255 levels
LINKS = (0.12, 0.11, 0.10, 0.06)  # base height, upper arm, forearm, hand (metres)


def arm_features(height: int = 480, width: int = 640, video: bool = True) -> dict:
    """LeRobot features of the recording (as an SO-101 follower records them)."""
    camera = {
        "dtype": "video" if video else "image",
        "shape": (height, width, 3),
        "names": ["height", "width", "channels"],
    }
    joints = {"dtype": "float32", "shape": (len(JOINTS),), "names": [f"{j}.pos" for j in JOINTS]}
    return {**{key: dict(camera) for key in CAMERAS}, "observation.state": dict(joints), "action": dict(joints)}


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


def teleoperated_episode(frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions (frames, 6) and the leader's targets (frames, 6): targets glide between random waypoints
    every 20–60 frames; the follower lags behind them (``LAG``)."""
    targets = np.empty((frames, len(JOINTS)), dtype=np.float32)
    current = rng.uniform(LOW * 0.5, HIGH * 0.5).astype(np.float32)
    t = 0
    while t < frames:
        span = int(rng.integers(20, 61))
        goal = rng.uniform(LOW, HIGH).astype(np.float32)
        ease = (1 - np.cos(np.linspace(0, np.pi, span, dtype=np.float32))) / 2
        targets[t : t + span] = (current + ease[:, None] * (goal - current))[: frames - t]
        current, t = goal, t + span
    positions = np.empty_like(targets)
    positions[0] = targets[0] + rng.normal(0, 2.0, len(JOINTS)).astype(np.float32)
    for i in range(1, frames):
        positions[i] = positions[i - 1] + LAG * (targets[i - 1] - positions[i - 1])
    return positions, targets


def _wait_for_encoder(dataset, poll_s: float = 0.002) -> None:
    """Block while a camera's streaming-encoder queue is full. LeRobot's writer drops a frame then (a live camera
    cannot wait); a generator can, and a dropped frame would leave a video shorter than its episode."""
    while any(queue.full() for queue in encoder_queues(dataset)):
        time.sleep(poll_s)


def encoder_queues(dataset) -> list:
    """The frame queues of the writer's streaming encoder for the episode being written (none before its first
    frame, or without streaming encoding)."""
    encoder = getattr(dataset.writer, "_streaming_encoder", None)
    return list(getattr(encoder, "_frame_queues", {}).values())


def write_arm_recording(
    root: str | Path,
    episodes: int,
    frames_per_episode: int,
    height: int = 480,
    width: int = 640,
    fps: int = 30,
    seed: int = 0,
    repo_id: str = "local/arm-recording",
    video: bool = True,
    vcodec: str = "libsvtav1",
    with_actions: bool = True,
    progress: bool = False,
):
    """Write the recording at ``root`` with ``LeRobotDataset.create`` → ``add_frame`` → ``save_episode`` →
    ``finalize``; episode ``i`` is drawn from seed ``seed + i``. ``with_actions=false`` leaves ``action`` out
    (a state-only recording). Returns the finalised ``LeRobotDataset``."""
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets import LeRobotDataset
    from tqdm.auto import tqdm

    features = arm_features(height, width, video)
    if not with_actions:
        features.pop("action")
    dataset = LeRobotDataset.create(
        repo_id, fps, features, root=root, robot_type="so101_follower", use_videos=video,
        rgb_encoder=RGBEncoderConfig(vcodec=vcodec) if video else None, streaming_encoding=video,
    )  # fmt: skip
    backgrounds = {key: _table(height, width, seed + n) for n, key in enumerate(CAMERAS)}
    # A camera's noise changes every frame (as a real sensor's does, and as a codec pays for): drawn from a bank.
    noise_rng = np.random.default_rng(seed + 10_000)
    noise_bank = noise_rng.normal(0.0, SENSOR_NOISE, size=(16, height, width, 3)).round().astype(np.int16)
    for episode in tqdm(range(episodes), desc="arm episodes", disable=not progress):
        positions, targets = teleoperated_episode(frames_per_episode, np.random.default_rng(seed + episode))
        for q, target in zip(positions, targets, strict=True):
            frame = {
                key: render(q, backgrounds[key], view, noise_bank[noise_rng.integers(len(noise_bank))])
                for key, view in zip(CAMERAS, ("front", "wrist"), strict=True)
            }
            frame["observation.state"] = q
            if with_actions:
                frame["action"] = target
            _wait_for_encoder(dataset)
            dataset.add_frame({**frame, "task": "move the arm"})
        dataset.save_episode()
    dataset.finalize()
    return dataset
