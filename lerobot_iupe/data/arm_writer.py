"""Writing the generator's recordings with LeRobot's own writer (``write_arm_recording``): the teleoperated arms of
``arm_recording`` and the hand-guided arm of ``hand_guided_arm``."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from lerobot_iupe.data.arm_recording import (
    CAMERAS,
    HUMANOID,
    OTHER_LEADER,
    SENSOR_NOISE,
    SO101,
    SO101_MISCALIBRATED,
    ArmBody,
    ArmDynamics,
    _table,
    arm_features,
    render,
    teleoperated_episode,
)
from lerobot_iupe.data.hand_guided_arm import VELOCITY_ARM, drawn_pose, hand_guided_episode, wrist_view
from lerobot_iupe.data.storage import no_image_embedding_without_images

BODIES = {body.name: body for body in (SO101, SO101_MISCALIBRATED, OTHER_LEADER, HUMANOID, VELOCITY_ARM)}


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
    dynamics: ArmDynamics | None = None,
    cameras: bool = True,
    body: ArmBody = SO101,
    idle: tuple[str, ...] = (),
):
    """Write the recording at ``root`` with ``LeRobotDataset.create`` → ``add_frame`` → ``save_episode`` →
    ``finalize``; episode ``i`` is drawn from seed ``seed + i``. ``with_actions=false`` leaves ``action`` out
    (a state-only recording); ``dynamics`` is how the follower follows the leader, ``body`` which arms record
    (``BODIES``), ``idle`` the leader joints that stay put; ``cameras=False`` writes the joints alone (quick data for
    the arm IDM, which reads only them; the cameras draw an SO-101 alone). Returns the finalised ``LeRobotDataset``."""
    from lerobot.configs.video import RGBEncoderConfig
    from lerobot.datasets import LeRobotDataset
    from tqdm.auto import tqdm

    if cameras and body.state_names not in (SO101.state_names, VELOCITY_ARM.state_names):
        raise ValueError(f"the cameras draw an SO-101; the {body.name} body is written with cameras=False")
    names = set(body.action_names) | (set(body.state_names) if body is VELOCITY_ARM else set())
    unknown = sorted(set(idle) - names)
    if unknown:
        raise ValueError(f"idle joints {unknown} are not among the {body.name} leader's {list(body.action_names)}")
    video = video and cameras
    dynamics = dynamics or ArmDynamics()
    features = arm_features(height, width, video, cameras, body)
    if not with_actions:
        features.pop("action")
    dataset = LeRobotDataset.create(
        repo_id, fps, features, root=root, robot_type=body.robot_type, use_videos=video,
        rgb_encoder=RGBEncoderConfig(vcodec=vcodec) if video else None, streaming_encoding=video,
    )  # fmt: skip
    backgrounds = {key: _table(height, width, seed + n) for n, key in enumerate(CAMERAS)}
    # A camera's noise changes every frame (as a real sensor's does, and as a codec pays for): drawn from a bank.
    noise_rng = np.random.default_rng(seed + 10_000)
    noise_bank = noise_rng.normal(0.0, SENSOR_NOISE, size=(16, height, width, 3)).round().astype(np.int16)
    for episode in tqdm(range(episodes), desc="arm episodes", disable=not progress):
        rng = np.random.default_rng(seed + episode)
        if body is VELOCITY_ARM:
            positions, targets, opening = hand_guided_episode(frames_per_episode, rng, fps, idle)
            poses = [drawn_pose(q, o) for q, o in zip(positions, opening, strict=True)]
        else:
            positions, targets = teleoperated_episode(frames_per_episode, rng, dynamics, body, idle)
            poses = positions
        openings = opening if body is VELOCITY_ARM else [None] * len(positions)
        for q, target, pose, jaws in zip(positions, targets, poses, openings, strict=True):
            frame = {}
            for key, view in zip(CAMERAS, ("front", "wrist"), strict=True) if cameras else ():
                noise = noise_bank[noise_rng.integers(len(noise_bank))]
                if jaws is not None and view == "wrist":  # a camera on the hand: it shows the jaws
                    frame[key] = wrist_view(q, jaws, backgrounds[key], noise)
                else:
                    frame[key] = render(pose, backgrounds[key], view, noise)
            frame["observation.state"] = q
            if with_actions:
                frame["action"] = target
            _wait_for_encoder(dataset)
            dataset.add_frame({**frame, "task": "move the arm"})
        with no_image_embedding_without_images():
            dataset.save_episode()
    dataset.finalize()
    return dataset
