"""Real camera data: two 480×640 cameras written by LeRobot's own writer, trained on and relabelled under a memory
cap; checkpoints that meet cameras of another size; the frame cache."""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import BIN, CHECKPOINT, once, run_in_process
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.arm_recording import CAMERAS
from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.data.episodes import EpisodeFrames
from lerobot_iupe.data.frame_cache import cache_dir, cached_frames
from lerobot_iupe.data.video import CameraFrames, resize_images
from lerobot_iupe.policy import IUPEPolicy
from lerobot_iupe.policy.networks import SpatialSelfAttention

# Address space for one training or relabelling process. Importing torch (a CUDA build) and LeRobot alone maps
# about 6 GB; the code before working resolutions needed 1.5 GB per 480×640 image for the attention of its first
# stage (19,200 positions), 12 GB for a batch of 8, and was killed on 40 frames.
MEMORY_CAP = 10 * 1024**3


def capped(*command: str, env: dict | None = None) -> subprocess.CompletedProcess:
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))

    return subprocess.run(
        command, capture_output=True, text=True, env={**os.environ, **(env or {})}, preexec_fn=limit, timeout=600
    )


def arm(data_dir: Path, name: str, **kwargs) -> Path:
    root = data_dir / name
    return once(root, lambda: write_arm_recording(root, repo_id=f"local/{name}", **kwargs), "meta/info.json")


@pytest.fixture(scope="session")
def arm_labelled(data_dir) -> Path:
    """Three episodes of an SO-101-shaped recording: two 480×640 cameras, joint state, joint targets."""
    return arm(data_dir, "arm-480", episodes=3, frames_per_episode=24)


@pytest.fixture(scope="session")
def arm_run(arm_labelled, shared_dir) -> Path:
    """A supervised camera IDM trained on it with default flags, under the memory cap; its output directory. The
    arm IDM (joint states alone) is turned off, so that the IDM reads the cameras."""
    out = shared_dir / "runs" / "arm"

    def train() -> None:
        result = capped(
            str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
            f"--dataset.repo_id=local/{arm_labelled.name}", f"--dataset.root={arm_labelled}",
            "--dataset.video_backend=pyav", "--batch_size=8", "--steps=6", "--save_freq=6", "--num_workers=0",
            "--policy.device=cpu", "--wandb.enable=false", f"--output_dir={out}", "--policy.joint_state_columns=[]",
        )  # fmt: skip
        assert result.returncode == 0, result.stderr[-3000:]

    return once(out, train, CHECKPOINT)


def test_a_supervised_idm_trains_on_two_480x640_cameras_under_the_memory_cap(arm_run):
    config = json.loads((arm_run / CHECKPOINT / "config.json").read_text())
    assert config["resize_shape"] == [72, 96]  # the default working resolution, recorded
    assert config["input_features"][CAMERAS[0]]["shape"] == [3, 480, 640]
    policy = IUPEPolicy.from_pretrained(arm_run / CHECKPOINT)
    assert policy.layout.shapes[0] == (3, 72, 96)


def test_a_480x640_video_dataset_is_relabelled_under_the_memory_cap(arm_run, data_dir):
    root = arm(data_dir, "arm-480-state-only", episodes=3, frames_per_episode=24, with_actions=False)
    result = capped(
        str(BIN / "lerobot-iupe-relabel"), f"--policy.path={arm_run / CHECKPOINT}", "--dataset.repo_id=local/x",
        f"--dataset.root={root}", "--dataset.video_backend=pyav", "--dry_run=true",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert "72 frames of 3 episodes labelled" in result.stdout


def test_relabelling_labels_what_the_policy_sees_of_lerobots_own_frames(arm_run, arm_labelled, tmp_path):
    """The labels written equal the IDM's outputs on frames decoded by LeRobot's own reader and resized by the
    policy's rule: the decoder-side resize feeds the IDM what lerobot-eval would."""
    root = tmp_path / "copy"
    write_arm_recording(root, 2, 12, repo_id="local/copy", with_actions=False, seed=7)
    run_in_process("lerobot-iupe-relabel", f"--policy.path={arm_run / CHECKPOINT}", "--dataset.repo_id=local/copy",
            f"--dataset.root={root}", "--dataset.video_backend=pyav", check=True)  # fmt: skip
    labelled = LeRobotDataset("local/copy", root=root, video_backend="pyav")
    policy = IUPEPolicy.from_pretrained(arm_run / CHECKPOINT).eval()
    items = [labelled[i] for i in range(12)]
    frames = policy.layout.join([torch.stack([item[k] for item in items]) for k in policy.config.observation_keys])
    offsets = policy.config.idm_window
    t = np.arange(11)
    window = frames[torch.as_tensor(np.clip(t[:, None] + np.array(offsets)[None, :], 0, 11))]
    with torch.no_grad():
        expected = policy.idm_head.mode(policy.idm_window_output(window)).numpy()
    written = torch.stack([item["action"] for item in items[:11]]).numpy()
    scale = np.asarray(policy.config.action_high) - np.asarray(policy.config.action_low)
    assert np.abs(written - expected).max(axis=0).max() / scale.max() < 0.02  # PyAV's scaler vs torch's: ~1 level


def test_a_checkpoint_relabels_cameras_of_another_size_as_it_sees_its_own(arm_run, data_dir):
    """The same recording at 240×320 is read at the checkpoint's 72×96: its labels match the 480×640 ones."""
    big = arm(data_dir, "arm-480-state-only", episodes=3, frames_per_episode=24, with_actions=False)
    small = arm(data_dir, "arm-240-state-only", episodes=3, frames_per_episode=24, with_actions=False,
                height=240, width=320)  # fmt: skip
    policy = IUPEPolicy.from_pretrained(arm_run / CHECKPOINT).eval()
    outputs = []
    for root in (big, small):
        dataset = LeRobotDataset("local/x", root=root, video_backend="pyav")
        reader = EpisodeFrames(dataset, {k: tuple(policy.config.resize_shape) for k in CAMERAS}, "pyav")
        parts = [reader.read(k, 0, 0, 23) for k in policy.config.observation_keys]
        frames = policy.layout.join(parts)
        window = torch.stack([frames[:-2], frames[1:-1], frames[2:], frames[2:]], dim=1)
        with torch.no_grad():
            outputs.append(policy.idm_window_output(window)[:, : policy.config.action_dim].numpy())
    spread = outputs[0].std(axis=0).mean()
    assert np.abs(outputs[0] - outputs[1]).mean() < 0.1 * spread


def test_select_action_resizes_an_env_camera_of_another_size(maze_run):
    """A 64×64 maze checkpoint acts on a 96×96 observation as on that observation resized to 64×64."""
    policy = IUPEPolicy.from_pretrained(maze_run / CHECKPOINT).eval()
    image = torch.rand(3, 3, 96, 96)
    policy.reset()
    big = policy.select_action({"observation.image": image})
    policy.reset()
    small = policy.select_action({"observation.image": resize_images(image, (64, 64))})
    assert torch.equal(big, small)


def test_lerobot_eval_plays_a_maze_rendered_at_another_size(maze_run, tmp_path):
    from conftest import evaluate

    overall = evaluate(maze_run / CHECKPOINT, tmp_path / "eval", "--env.type=maze", "--env.size=3",
                       "--env.image_size=96", episodes=2)  # fmt: skip
    assert overall["n_episodes"] == 2


def test_the_generator_waits_for_lerobots_encoder_so_every_video_holds_its_episode(arm_labelled, tmp_path):
    """LeRobot's streaming encoder drops a frame when its queue is full (as on a loaded CI machine); the generator
    waits on those queues, so it must find them on LeRobot's real writer."""
    import av

    from lerobot_iupe.data.arm_recording import arm_features
    from lerobot_iupe.data.arm_writer import encoder_queues

    dataset = LeRobotDataset.create("local/q", 30, arm_features(48, 64, True), root=tmp_path / "q",
                                    use_videos=True, streaming_encoding=True)  # fmt: skip
    frame = {key: np.zeros((48, 64, 3), np.uint8) for key in CAMERAS}
    dataset.add_frame({**frame, "observation.state": np.zeros(6, np.float32),
                       "action": np.zeros(6, np.float32), "task": "t"})  # fmt: skip
    assert len(encoder_queues(dataset)) == len(CAMERAS)
    dataset.save_episode()
    dataset.finalize()

    written = LeRobotDataset("local/arm-480", root=arm_labelled, video_backend="pyav")
    for key in CAMERAS:
        for path in sorted((arm_labelled / "videos" / key).rglob("*.mp4")):
            with av.open(str(path)) as container:
                assert sum(1 for _ in container.decode(video=0)) == written.meta.total_frames


@pytest.mark.parametrize("backend", ["pyav", "torchcodec"])
def test_frames_at_the_working_size_are_lerobots_frames_of_the_same_time_in_rgb(arm_labelled, backend):
    """The decoder-side scaler gives (n, 3, 96, 128) uint8 frames that match LeRobot's own decoded frames of the same
    index, resized by the policy's rule, within a few levels; the neighbouring frames and the channels reversed (BGR)
    are farther off. One decoding thread per process, whatever the codec."""
    dataset = LeRobotDataset("local/arm-480", root=arm_labelled, video_backend="pyav")
    key, episode = CAMERAS[1], 1
    first, end = (int(dataset.meta.episodes[episode][c]) for c in ("dataset_from_index", "dataset_to_index"))
    camera = CameraFrames(dataset.meta, backend, (96, 128))
    decoded = camera.frames(key, episode, first + 4, end - 5).float()
    assert decoded.shape == (end - first - 8, 3, 96, 128)
    lerobots = torch.stack([dataset[i][key] for i in range(first, end)]) * 255  # float RGB 0–1, full size
    resized = resize_images(lerobots, (96, 128))
    same = (decoded - resized[4:-4]).abs().mean()
    assert same < 3.0
    assert min((decoded - resized[4 + shift : len(resized) - 4 + shift]).abs().mean() for shift in (-1, 1)) > same
    assert (decoded.flip(1) - resized[4:-4]).abs().mean() > 3 * same
    container = camera._decoders[next(iter(camera._decoders))]
    assert container.streams.video[0].codec_context.thread_count == 1
    # at the stored size the backend asked for decodes (torchcodec's own frames, faster on small videos)
    assert CameraFrames.decoder_name(backend, (480, 640), (480, 640)) == backend


def test_the_frame_cache_is_reused_and_rebuilt_when_the_dataset_changes(data_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("LEROBOT_IUPE_CACHE", str(tmp_path / "cache"))
    root = tmp_path / "arm"
    write_arm_recording(root, 2, 10, repo_id="local/arm", seed=3)
    dataset = LeRobotDataset("local/arm", root=root, video_backend="pyav")
    key = CAMERAS[0]
    frames = cached_frames(dataset, key, (96, 128), "pyav", progress=False)
    decoded = torch.cat([CameraFrames(dataset.meta, "pyav", (96, 128)).frames(key, e, 10 * e, 10 * e + 9)
                         for e in range(2)])  # fmt: skip
    assert frames.shape == (20, 3, 96, 128) and np.array_equal(frames, decoded.numpy())
    (built,) = cache_dir().glob("*.npy")
    stamp = built.stat().st_mtime_ns

    again = cached_frames(LeRobotDataset("local/arm", root=root, video_backend="pyav"), key, (96, 128), "pyav")
    assert list(cache_dir().glob("*.npy")) == [built] and built.stat().st_mtime_ns == stamp
    assert np.array_equal(again, frames)

    other = tmp_path / "other"  # the same path recorded again with other motions: the dataset changed
    write_arm_recording(other, 2, 10, repo_id="local/arm", seed=4)
    for path in root.iterdir():
        subprocess.run(["rm", "-rf", str(path)], check=True)
    for path in other.iterdir():
        path.rename(root / path.name)
    changed = LeRobotDataset("local/arm", root=root, video_backend="pyav")
    rebuilt = cached_frames(changed, key, (96, 128), "pyav", progress=False)
    assert len(list(cache_dir().glob("*.npy"))) == 2
    fresh = CameraFrames(changed.meta, "pyav", (96, 128)).frames(key, 0, 0, 9).numpy()
    assert np.array_equal(rebuilt[:10], fresh) and not np.array_equal(rebuilt, frames)


def test_attention_is_the_full_sagan_product_on_small_maps_and_bounded_on_large_ones():
    torch.manual_seed(0)
    attention = SpatialSelfAttention(16)
    attention.gamma.data.fill_(0.7)
    x = torch.randn(2, 16, 16, 16)
    q, k = attention.query(x).flatten(2).transpose(1, 2), attention.key(x).flatten(2)
    full = x + attention.gamma * (attention.value(x).flatten(2) @ torch.softmax(q @ k, -1).transpose(1, 2)).view(
        x.shape
    )
    assert torch.allclose(attention(x), full, atol=1e-6)
    assert SpatialSelfAttention.grid(24, 32) == (13, 18)  # 234 of 768 positions
    assert SpatialSelfAttention.grid(120, 160) == (13, 18)
    big = torch.randn(1, 16, 120, 160)
    out = attention(big)
    assert out.shape == big.shape and not torch.allclose(out, big)


def test_a_relabel_whose_decoding_process_dies_stops_with_an_error(arm_run, data_dir, monkeypatch):
    """A decoder killed from outside (as the kernel kills for memory) ends the relabel with an error, not a hang."""
    import signal

    from lerobot_iupe.relabel import labelling
    from lerobot_iupe.relabel.config import RelabelConfig
    from lerobot_iupe.relabel.run import relabel

    def killed(*args) -> None:
        os.kill(os.getpid(), signal.SIGKILL)

    monkeypatch.setattr(labelling, "_work", killed)
    root = arm(data_dir, "arm-480-state-only", episodes=3, frames_per_episode=24, with_actions=False)
    config = RelabelConfig()
    config.policy.path, config.dataset.root, config.dataset.repo_id = str(arm_run / CHECKPOINT), str(root), "local/x"
    config.dataset.video_backend, config.dry_run = "pyav", True
    with pytest.raises(RuntimeError, match="died"):
        relabel(config)


def test_the_next_frame_cache_build_deletes_the_half_written_file_of_a_killed_one(arm_labelled, tmp_path, monkeypatch):
    """A build killed (SIGKILL, out of memory) leaves its ``.partial-<pid>.npy``, which nothing reads; the next
    build deletes it, and leaves a live build's file alone."""
    cache = tmp_path / "cache"
    cache.mkdir()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    killed = cache / f".0123456789abcdef01234567.partial-{int(dead.stdout)}.npy"
    live = cache / f".0123456789abcdef01234567.partial-{os.getpid()}.npy"
    killed.write_bytes(b"half")
    live.write_bytes(b"being written")
    monkeypatch.setenv("LEROBOT_IUPE_CACHE", str(cache))
    dataset = LeRobotDataset("local/x", root=arm_labelled, video_backend="pyav")
    frames = cached_frames(dataset, CAMERAS[0], (96, 128), "pyav", progress=False)
    assert frames.shape == (72, 3, 96, 128)
    assert not killed.exists() and live.exists()


@pytest.mark.parametrize("shape", [[96], [96, 128, 3], [4, 128]])
def test_a_malformed_resize_shape_is_refused_naming_the_flag(shape):
    from lerobot_iupe.policy import IUPEConfig

    with pytest.raises(ValueError, match=r"--policy.resize_shape must be \[height, width\] of at least 8 pixels"):
        IUPEConfig(resize_shape=shape)


def test_a_camera_with_other_channels_is_refused_naming_both_sides():
    from lerobot_iupe.data.compat import DataSpec, check_compatible

    checkpoint = DataSpec("the checkpoint", CAMERAS[0], (480, 640, 3))
    check_compatible(checkpoint, DataSpec("a smaller dataset", CAMERAS[0], (240, 320, 3)))  # any size is resized
    with pytest.raises(ValueError, match="has 1 channels in the depth dataset but 3 in the checkpoint"):
        check_compatible(checkpoint, DataSpec("the depth dataset", CAMERAS[0], (480, 640, 1)))


@pytest.fixture(scope="session")
def arm_joint_run(arm_labelled, shared_dir) -> Path:
    """lerobot-train with default flags on the camera recording: the policy reads the cameras, the IDM is the
    arm's (joint states alone)."""
    out = shared_dir / "runs" / "arm-joint"

    def train() -> None:
        run_in_process(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true",
            f"--dataset.repo_id=local/{arm_labelled.name}", f"--dataset.root={arm_labelled}",
            "--dataset.video_backend=pyav", "--batch_size=8", "--steps=4", "--save_freq=4", "--num_workers=0",
            "--policy.device=cpu", "--wandb.enable=false", f"--output_dir={out}", check=True
        )  # fmt: skip

    return once(out, train, CHECKPOINT)


def test_the_arm_idm_relabels_without_decoding_a_camera(arm_joint_run, data_dir, tmp_path):
    """The policy reads the cameras, but its IDM reads the joint states: relabelling a recording whose videos
    cannot be decoded labels every frame all the same."""
    config = json.loads((arm_joint_run / CHECKPOINT / "config.json").read_text())
    assert config["joint_state_columns"] == list(range(6)) and CAMERAS[0] in config["observation_keys"]
    source = arm(data_dir, "arm-480-state-only", episodes=3, frames_per_episode=24, with_actions=False)
    root = tmp_path / "broken-videos"
    shutil.copytree(source, root)
    videos = sorted((root / "videos").rglob("*.mp4"))
    assert videos
    for video in videos:
        video.write_bytes(b"not a video")
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={arm_joint_run / CHECKPOINT}", "--dataset.repo_id=local/x",
        f"--dataset.root={root}", "--dataset.video_backend=pyav", "--dry_run=true", check=True,
    )  # fmt: skip
    assert "72 frames of 3 episodes labelled" in result.stdout
