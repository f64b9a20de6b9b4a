import json

import numpy as np
import pytest
from conftest import collect as collect_fixture
from conftest import run_cli, run_in_process
from lerobot.datasets import LeRobotDataset

from lerobot_iupe import collect as collect_module
from lerobot_iupe.collect import CollectConfig, collect
from lerobot_iupe.data.readers import stored_frames
from lerobot_iupe.data.storage import DatasetTarget, read_iupe_meta
from lerobot_iupe.envs import CartPoleEnvConfig, MazeEnvConfig


def test_expert_dataset_is_state_only_and_complete(cartpole_expert):
    dataset = LeRobotDataset("local/cartpole-expert", root=cartpole_expert)
    assert "action" not in dataset.features
    assert dataset.meta.total_episodes == 10
    assert dataset.meta.total_frames == 10 * 501  # 500 steps + the terminal observation
    meta = read_iupe_meta(cartpole_expert)
    assert meta["env"]["type"] == "cartpole" and meta["agent"] == "expert" and meta["seeds"][0] == 0
    assert meta["mean_return"] == 500.0
    frame = dataset[500]
    assert bool(frame["next.done"]) and float(frame["next.reward"]) == 0.0
    assert dataset[0]["observation.state"].shape == (4,)


def test_random_maze_video_dataset_has_actions_and_layouts(maze_random):
    dataset = LeRobotDataset("local/maze3-random", root=maze_random, video_backend="pyav")
    assert dataset.features["observation.image"]["dtype"] == "video"
    assert dataset.features["action"]["dtype"] == "int64"
    frame = dataset[1]
    assert frame["observation.image"].shape == (3, 64, 64)
    assert 0 <= int(frame["action"]) < 4
    meta = read_iupe_meta(maze_random)
    assert meta["layout_ids"] == list(range(50, 56)) and meta["env"]["size"] == 3


def test_maze_frames_stored_as_png_are_the_env_frames(data_dir):
    root = collect_fixture(
        data_dir, "maze3-png", "--env.type=maze", "--env.size=3", "--env.image_size=21", "--agent=expert",
        "--episodes=2", "--keep_actions=true", "--video=false",
    )  # fmt: skip
    dataset = LeRobotDataset("local/maze3-png", root=root)
    assert dataset.features["observation.image"]["dtype"] == "image"
    assert not (root / "videos").exists()
    frames = stored_frames(dataset, "observation.image")
    assert frames.dtype == np.uint8 and frames.shape == (dataset.meta.total_frames, 3, 21, 21)
    env = MazeEnvConfig(size=3, image_size=21).make()
    observation, _ = env.reset(seed=0, options={"layout_id": 0})
    replay = [observation["pixels"]]
    for i in range(int(dataset.meta.episodes["length"][0]) - 1):
        observation = env.step(int(dataset[i]["action"]))[0]
        replay.append(observation["pixels"])
    assert np.array_equal(frames[: len(replay)], np.stack(replay).transpose(0, 3, 1, 2))  # lossless
    assert np.allclose(dataset[3]["observation.image"].numpy(), frames[3] / 255.0)  # LeRobot reads the same


def test_keep_actions_stores_expert_actions(data_dir):
    root = data_dir / "cartpole-expert-actions"
    run_cli(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=expert",
        "--episodes=1",
        "--keep_actions=true",
        "--dataset.repo_id=local/x",
        f"--dataset.root={root}",
    )
    dataset = LeRobotDataset("local/x", root=root)
    states = np.stack([dataset[i]["observation.state"].numpy() for i in range(20)])
    actions = np.array([int(dataset[i]["action"]) for i in range(20)])
    expected = (states @ np.array([0.1, 0.5, 10.0, 1.0]) > 0).astype(int)
    assert np.array_equal(actions, expected)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env.type=pendulum"], "env.type"),
        (["--env.type=cartpole", "--agent=oracle"], "--agent=oracle"),
        (["--env.type=cartpole", "--episodes=0"], "--episodes must be a positive"),
        (["--env.type=maze", "--env.size=1"], "--env.size must be at least 2"),
        (["--env.type=cartpole", "--random_start=true"], "--random_start"),
        (["--env.type=cartpole", "--video=false"], "--video=false only applies"),
        (["--env.type=cartpole", "--push_to_hub=true"], "--push_to_hub is now --dataset.push_to_hub"),
    ],
)
def test_bad_input_is_refused_and_writes_nothing(tmp_path, args, message):
    root = tmp_path / "ds"
    result = run_in_process("lerobot-iupe-collect", *args, "--dataset.repo_id=local/x", f"--dataset.root={root}")
    assert result.returncode != 0
    assert message in result.stderr + result.stdout
    assert not root.exists() and list(tmp_path.iterdir()) == []


def test_existing_root_is_refused_and_untouched(cartpole_expert):
    before = {p: p.stat().st_mtime_ns for p in cartpole_expert.rglob("*")}
    result = run_cli(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--dataset.repo_id=local/x",
        f"--dataset.root={cartpole_expert}",
        check=False,
    )
    assert result.returncode == 2 and "--overwrite=true" in result.stderr
    assert {p: p.stat().st_mtime_ns for p in cartpole_expert.rglob("*")} == before


def test_overwrite_replaces_only_after_completion(tmp_path, monkeypatch):
    root = tmp_path / "ds"
    cfg = CollectConfig(env=CartPoleEnvConfig(), dataset=DatasetTarget("local/x", str(root)), episodes=2)
    collect(cfg)
    info_before = (root / "meta" / "info.json").read_text()

    def failing_agent(env, observation):
        raise RuntimeError("disk full")

    monkeypatch.setattr(collect_module, "make_agent", lambda *a: failing_agent)
    cfg.overwrite, cfg.agent = True, "random"
    with pytest.raises(RuntimeError, match="disk full"):
        collect(cfg)
    assert (root / "meta" / "info.json").read_text() == info_before
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]  # no staged leftovers
    monkeypatch.undo()
    collect(cfg)
    assert json.loads((root / "meta" / "info.json").read_text())["features"]["action"]["dtype"] == "int64"
    assert [p.name for p in tmp_path.iterdir()] == ["ds"]
