import contextlib
import dataclasses
import json

import numpy as np
import pytest
from conftest import CHECKPOINT, evaluate, run_cli, run_in_process, train_args
from conftest import collect as collect_fixture
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


def test_skipping_lerobots_image_embedding_writes_the_same_rows_and_restores_it(tmp_path, monkeypatch):
    """The writer's row-by-row image map is skipped where no column holds an image: the same parquet rows as
    LeRobot's own writer (the PNG maze test above checks that images are still embedded)."""
    import pyarrow.parquet as pq
    from lerobot.datasets import dataset_writer

    embed_images, calls = dataset_writer.embed_images, []

    def counted(dataset):
        calls.append(len(dataset))
        return embed_images(dataset)

    monkeypatch.setattr(dataset_writer, "embed_images", counted)
    lerobots = CollectConfig(env=CartPoleEnvConfig(), dataset=DatasetTarget("local/x", str(tmp_path / "a")), episodes=3)
    with monkeypatch.context() as patch:
        patch.setattr(collect_module, "no_image_embedding_without_images", contextlib.nullcontext)
        collect(lerobots)
    assert len(calls) == 3  # LeRobot's map ran once per episode
    collect(dataclasses.replace(lerobots, dataset=DatasetTarget("local/x", str(tmp_path / "b"))))
    assert len(calls) == 3 and dataset_writer.embed_images is counted  # skipped, then LeRobot's put back
    tables = [pq.read_table(tmp_path / name / "data/chunk-000/file-000.parquet") for name in "ab"]
    assert tables[0].num_rows > 3 and tables[0].equals(tables[1])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env.type=pendulum"], "env.type"),
        (["--env.type=cartpole", "--agent=oracle"], "--agent=oracle"),
        (["--env.type=cartpole", "--episodes=0"], "--episodes must be a positive"),
        (["--env.type=maze", "--env.size=1"], "--env.size must be at least 2"),
        (["--env.type=cartpole", "--random_start=true"], "--random_start"),
        (["--env.type=cartpole", "--video=false"], "--video=false only applies"),
        (["--env.type=so101_pickplace", "--video=false"], "--env.image_obs=true"),
        (["--env.type=so101_pickplace", "--env.image_obs=true", "--env.image_size=8"], "--env.image_size must be"),
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
    result = run_in_process(
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


def test_the_so101_front_camera_renders_the_arm_and_records_a_camera_and_state_video_dataset(data_dir):
    from lerobot_iupe.envs.configs import SO101PickPlaceEnvConfig

    env = SO101PickPlaceEnvConfig(image_obs=True, image_size=48).make()
    observation, _ = env.reset(seed=0)
    first = observation["pixels"]["front"]
    assert set(observation) == {"agent_pos", "pixels"} and first.shape == (48, 48, 3) and first.dtype == np.uint8
    assert first.std() > 10  # a scene, not a blank frame
    for _ in range(5):
        observation = env.step(env.get_wrapper_attr("expert_action")())[0]
    assert np.abs(observation["pixels"]["front"].astype(int) - first).sum() > 0  # the arm moved in the picture
    env.close()

    root = collect_fixture(
        data_dir, "so101-camera", "--env.type=so101_pickplace", "--env.image_obs=true", "--env.image_size=48",
        "--env.episode_length=15", "--agent=play", "--episodes=2",
    )  # fmt: skip
    dataset = LeRobotDataset("local/so101-camera", root=root, video_backend="pyav")
    assert dataset.features["observation.images.front"]["dtype"] == "video"
    assert dataset.features["observation.state"]["shape"] == (14,)
    assert "observation.environment_state" not in dataset.features  # the block and goal are seen, not read
    assert dataset.meta.total_frames == 2 * 16 and dataset[3]["observation.images.front"].shape == (3, 48, 48)
    assert read_iupe_meta(root)["env"] | {"image_obs": True, "image_size": 48} == read_iupe_meta(root)["env"]


def test_iupe_trains_and_lerobot_eval_runs_on_the_arms_camera_and_state(data_dir, tmp_path):
    """The IUPE cycle (pre-demonstrations, rollouts rendered in the env, I^s) and lerobot-eval with the front camera
    and observation.state fused; a tiny budget: this checks the paths, benchmarks measure learning."""
    camera = ["--env.type=so101_pickplace", "--env.image_obs=true", "--env.image_size=48", "--env.episode_length=12"]
    expert = collect_fixture(data_dir, "so101-camera-expert", *camera, "--agent=expert", "--episodes=2")
    play = collect_fixture(data_dir, "so101-camera-play", *camera, "--agent=play", "--episodes=2", "--seed=100")
    run_in_process(
        "lerobot-train", *train_args(expert, play, tmp_path / "run"), "--steps=4", "--save_freq=4", "--batch_size=8",
        "--policy.cycle_steps=2", "--policy.rollout_episodes=2", "--policy.idm_epochs=1", "--policy.torch_threads=1",
        check=True,
    )  # fmt: skip
    checkpoint = tmp_path / "run" / CHECKPOINT
    config = json.loads((checkpoint / "config.json").read_text())
    assert config["observation_keys"] == ["observation.images.front", "observation.state"]
    cycles = [json.loads(line) for line in (checkpoint / "iupe_cycles.jsonl").read_text().splitlines()]
    assert len(cycles) == 2
    result = evaluate(checkpoint, tmp_path / "eval", *camera, episodes=1)
    assert result["n_episodes"] == 1 and np.isfinite(result["avg_sum_reward"])
