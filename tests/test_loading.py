"""Reading each frame once: lerobot-train's loader decodes no camera the policy does not read from it, and a
relabel decoded by several processes writes exactly the labels of one."""

from __future__ import annotations

import json
import shutil

import lerobot.datasets.dataset_reader as dataset_reader
import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, run_in_process
from lerobot.datasets import LeRobotDataset
from test_real_cameras import arm

from lerobot_iupe.data.arm_recording import CAMERAS
from lerobot_iupe.data.loader_view import stop_decoding_cameras
from lerobot_iupe.data.readers import action_array


@pytest.fixture(scope="module")
def arm_small(data_dir):
    """Three episodes of the two-camera 480×640 arm recording."""
    return arm(data_dir, "arm-480-small", episodes=3, frames_per_episode=20)


@pytest.fixture(scope="module")
def camera_run(arm_small, tmp_path_factory):
    """A camera IDM trained in this process by lerobot-train (4 batches of 8), with every call of LeRobot's video
    decoder counted: (output directory, decoded files)."""
    calls = []
    decode = dataset_reader.decode_video_frames

    def counted(video_path, *args, **kwargs):
        calls.append(str(video_path))
        return decode(video_path, *args, **kwargs)

    out = tmp_path_factory.mktemp("loading") / "train"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(dataset_reader, "decode_video_frames", counted)
        result = run_in_process(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", "--policy.joint_state_columns=[]",
            f"--dataset.repo_id=local/{arm_small.name}", f"--dataset.root={arm_small}",
            "--dataset.video_backend=pyav", "--batch_size=8", "--steps=4", "--save_freq=4", "--num_workers=0",
            "--policy.device=cpu", "--wandb.enable=false", f"--output_dir={out}",
        )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    return out, calls


def test_lerobot_train_decodes_no_camera_frame_for_the_policy(camera_run):
    """The policy reads its frames from the package's cache by the batch's index: LeRobot's loader, which would
    decode both cameras of every item (64 calls for 4 batches of 8), decodes none. The policy still reads both
    cameras (the camera IDM)."""
    out, calls = camera_run
    assert (out / CHECKPOINT / "model.safetensors").exists()
    config = json.loads((out / CHECKPOINT / "config.json").read_text())
    assert set(CAMERAS) <= set(config["observation_keys"]) and config["joint_state_columns"] == []
    assert calls == [], f"LeRobot's loader decoded {len(calls)} camera frames the policy never reads"


def test_a_loader_without_cameras_keeps_every_other_column(arm_small):
    """The lean reader's items are LeRobot's items, value for value, but for the cameras' empty placeholders."""
    full = LeRobotDataset(f"local/{arm_small.name}", root=arm_small, video_backend="pyav")
    lean = LeRobotDataset(f"local/{arm_small.name}", root=arm_small, video_backend="pyav")
    assert sorted(stop_decoding_cameras(lean)) == sorted(CAMERAS)
    assert set(CAMERAS) <= set(lean.meta.video_keys)  # the dataset's own metadata is untouched
    for row in (0, 7, len(full) - 1):
        expected, got = full[row], lean[row]
        assert set(expected) == set(got)
        for key, value in got.items():
            if key in CAMERAS:
                assert value.shape == (0,) and expected[key].shape == (3, 480, 640)
            else:
                assert np.array_equal(np.asarray(value), np.asarray(expected[key])), key


def test_a_relabel_by_worker_processes_writes_the_labels_of_one_process(camera_run, arm_small, data_dir, tmp_path):
    """Draws (--mode=sample), several spans per episode (--batch_size=8): the labels of three worker processes and
    of none (all in the calling process) are the same to the bit."""
    source = arm(data_dir, "arm-480-small-state-only", episodes=3, frames_per_episode=20, with_actions=False)
    labels = {}
    for workers in (0, 3):
        root = tmp_path / f"workers-{workers}"
        shutil.copytree(source, root)
        run_in_process(
            "lerobot-iupe-relabel", f"--policy.path={camera_run[0] / CHECKPOINT}", "--dataset.repo_id=local/x",
            f"--dataset.root={root}", "--dataset.video_backend=pyav", "--mode=sample", "--batch_size=8",
            f"--num_workers={workers}", check=True,
        )  # fmt: skip
        labels[workers] = action_array(LeRobotDataset("local/x", root=root))
    assert labels[0].shape == (60, 6) and np.isfinite(labels[0]).all()
    assert np.array_equal(labels[3], labels[0])


def test_workers_that_only_decode_feed_the_first_process_the_same_outputs(camera_run, arm_small):
    """The GPU's pipeline (workers decode, the first process runs the IDM), run on the CPU: every span's IDM
    outputs equal those of decoding and labelling in one process, each episode's spans in order."""
    from lerobot_iupe.data.readers import FrameReader, episode_bounds, label_spans
    from lerobot_iupe.relabel.checks import check_labelable, load_idm
    from lerobot_iupe.relabel.labelling import outputs_in_process, outputs_in_workers

    policy = load_idm(str(camera_run[0] / CHECKPOINT))
    dataset = LeRobotDataset(f"local/{arm_small.name}", root=arm_small, video_backend="pyav")
    keys = check_labelable(policy, dataset.meta, overwrite=True, dry_run=True)
    reader = FrameReader(dataset, keys, policy.config.layout_of(keys), "pyav")
    spans = label_spans(episode_bounds(dataset.meta), 8, policy.config.idm_window)
    expected = list(outputs_in_process(policy, reader, spans, "cpu"))
    got = list(outputs_in_workers(policy, reader, spans, 2, "cpu", label_in_workers=False))
    assert len(got) == len(expected) == len(spans) > 3
    for episode in {span.episode for span in spans}:
        mine = [(s, o) for s, o in got if s.episode == episode]
        theirs = [(s, o) for s, o in expected if s.episode == episode]
        assert [s for s, _ in mine] == [s for s, _ in theirs]
        assert all(torch.equal(a, b) for (_, a), (_, b) in zip(mine, theirs, strict=True))
