"""Meta-World through LeRobot's own env, observed as state: the experts' state-only datasets, the play agent,
an IUPE checkpoint under lerobot-eval, and a wrong task name."""

import json
import os
import subprocess

import numpy as np
import pytest
from conftest import BIN, CHECKPOINT, collect, evaluate, run_in_process, train_args, train_once
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.envs.metaworld_config import METAWORLD_MT10, MetaWorldStateEnvConfig
from lerobot_iupe.experts import make_agent

TASK = "--env.task=push-v3"


@pytest.fixture(scope="module")
def push_expert(data_dir):
    return collect(data_dir, "mw-push-expert", "--env.type=metaworld_state", TASK, "--agent=expert", "--episodes=3")


@pytest.fixture(scope="module")
def push_play(data_dir):
    return collect(
        data_dir, "mw-push-play", "--env.type=metaworld_state", TASK, "--env.episode_length=100", "--agent=play",
        "--episodes=4", "--seed=1000",
    )  # fmt: skip


def test_expert_episodes_are_stored_without_actions_and_every_one_succeeds(push_expert):
    dataset = LeRobotDataset("local/mw-push-expert", root=push_expert)
    assert "action" not in dataset.features
    features = dataset.meta.features
    assert tuple(features["observation.environment_state"]["shape"]) == (39,)
    assert features["observation.environment_state"]["names"][36:] == ["goal.x", "goal.y", "goal.z"]
    assert features["observation.state"]["names"] == ["hand.x", "hand.y", "hand.z", "gripper.opening"]
    meta = read_iupe_meta(push_expert)
    assert meta["success_rate"] == 1.0 and meta["env"] == {"type": "metaworld_state", "task": "push-v3",
                                                           "episode_length": 500, "play_held_moves": 0.5}  # fmt: skip
    ends = np.cumsum(dataset.meta.episodes["length"]) - 1
    assert [bool(dataset[int(i)]["next.success"]) for i in ends] == [True] * 3
    assert all(length < 200 for length in dataset.meta.episodes["length"])  # an episode ends at its first success
    state = np.stack([dataset[i]["observation.environment_state"].numpy() for i in range(3)])
    assert np.allclose(state[:, :4], np.stack([dataset[i]["observation.state"].numpy() for i in range(3)]))


def test_the_state_variant_steps_where_mujoco_cannot_render(tmp_path):
    """The collect command as a process with MuJoCo's OpenGL switched off: nothing in it may render."""
    root = tmp_path / "reach"
    result = subprocess.run(
        [str(BIN / "lerobot-iupe-collect"), "--env.type=metaworld_state", "--env.task=reach-v3", "--agent=expert",
         "--episodes=1", "--dataset.repo_id=local/reach", f"--dataset.root={root}"],
        capture_output=True, text=True, env={**os.environ, "MUJOCO_GL": "disable"}, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert read_iupe_meta(root)["success_rate"] == 1.0


@pytest.mark.parametrize("task", METAWORLD_MT10)
def test_each_mt10_expert_succeeds_and_play_does_not_by_chance(task):
    env = MetaWorldStateEnvConfig(task=task).make()
    expert, play = make_agent("metaworld_state", "expert"), make_agent("metaworld_state", "play")
    observation, _ = env.reset(seed=7)
    for _ in range(500):
        observation, _, terminated, truncated, info = env.step(expert(env, observation))
        if terminated or truncated:
            break
    assert terminated and info["is_success"]
    observation, _ = env.reset(seed=7)
    hands, grasps = [], []
    for _ in range(200):
        action = play(env, observation)
        observation, _, terminated, truncated, info = env.step(action)
        hands.append(observation["agent_pos"][:3])
        grasps.append(action[3])
    env.close()
    hands = np.stack(hands)
    assert (hands.max(0) - hands.min(0))[:2].min() > 0.1  # play moves the hand across the table
    assert min(grasps) < 0 < max(grasps)  # and both opens and shuts the gripper


def play_commands(held_moves: float, steps: int = 300) -> np.ndarray:
    env = MetaWorldStateEnvConfig(task="reach-v3", play_held_moves=held_moves).make()
    observation, _ = env.reset(seed=3)
    play, commands = make_agent("metaworld_state", "play"), []
    for _ in range(steps):
        action = play(env, observation)
        commands.append(action[:3])
        observation, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:  # reach can succeed by chance: play on from a new episode
            observation, _ = env.reset()
    env.close()
    return np.stack(commands)


def test_held_moves_keep_a_command_at_the_bounds_as_the_experts_do():
    """Held moves (``--env.play_held_moves``) keep one hand command for 10-40 steps, often at ±1; moves toward a
    target (share 0, the first results' play) slow down as they near it and seldom reach the bounds."""
    held, steered = play_commands(1.0), play_commands(0.0)
    steady = np.abs(np.diff(held, axis=0)).max(axis=1) < 0.6  # one command plus its N(0, 0.1) noise
    assert steady.mean() > 0.9
    assert np.mean(np.abs(held) > 0.95) > 0.2 > 0.05 > np.mean(np.abs(steered) > 0.95)
    with pytest.raises(ValueError, match="--env.play_held_moves"):
        MetaWorldStateEnvConfig(task="reach-v3", play_held_moves=1.5).validate()


def test_play_reads_the_hand_only():
    """Two episodes whose object and goal differ (their seeds) played from the same generator: the same actions."""
    actions, goals = [], []
    for seed in (1, 2):
        env = MetaWorldStateEnvConfig(task="pick-place-v3").make()
        observation, _ = env.reset(seed=seed)
        goals.append(observation["environment_state"][36:])
        env.unwrapped.np_random = np.random.default_rng(0)
        play, played = make_agent("metaworld_state", "play"), []
        for _ in range(30):
            played.append(play(env, observation))
            observation = env.step(played[-1])[0]
        actions.append(np.stack(played))
        env.close()
    assert not np.allclose(goals[0], goals[1])
    assert np.allclose(actions[0], actions[1], atol=1e-5)


def test_lerobot_eval_scores_an_iupe_checkpoint_on_the_state_variant(push_expert, push_play, shared_dir, tmp_path):
    out = shared_dir / "runs" / "mw-push"
    flags = [
        "--steps=4",
        "--batch_size=16",
        "--save_freq=4",
        "--policy.cycle_steps=2",
        "--policy.rollout_episodes=1",
        "--policy.selection_episodes=1",
        "--policy.idm_epochs=1",
        "--env.type=metaworld_state",
        TASK,
        "--env.episode_length=50",
        "--policy.idm_context=3",
        "--policy.idm_observation_keys=[observation.state]",
    ]
    run = train_once(out, *train_args(push_expert, push_play, out, *flags))
    config = json.loads((run / CHECKPOINT / "config.json").read_text())
    assert config["env_settings"] == {
        "type": "metaworld_state", "task": "push-v3", "episode_length": 50, "play_held_moves": 0.5
    }  # fmt: skip
    # the cycle ran on windows of the hand's state (the benchmark's setting): two cycles, the IDM scored on them
    assert config["idm_context"] == 3 and config["idm_observation_keys"] == ["observation.state"]
    cycles = [json.loads(line) for line in (run / CHECKPOINT / "iupe_cycles.jsonl").read_text().splitlines()]
    assert len(cycles) == 2 and all(np.isfinite(c["idm_r2"]) for c in cycles)
    overall = evaluate(run / CHECKPOINT, tmp_path / "eval", "--env.type=metaworld_state", TASK, episodes=2)
    assert overall["n_episodes"] == 2 and 0.0 <= overall["pc_success"] <= 100.0
    assert len(list((tmp_path / "eval" / "videos").rglob("*.mp4"))) == 2  # lerobot-eval's videos: the sketch


def test_a_wrong_task_name_is_one_line_naming_the_flag_and_the_tasks(tmp_path):
    root = tmp_path / "data"
    result = run_in_process(
        "lerobot-iupe-collect", "--env.type=metaworld_state", "--env.task=push-v2", "--agent=expert", "--episodes=1",
        "--dataset.repo_id=local/x", f"--dataset.root={root}",
    )  # fmt: skip
    assert result.returncode == 2 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert "--env.task" in line and "'push-v2'" in line and "push-v3" in line and "peg-insert-side-v3" in line
    assert not root.exists()


def test_a_share_of_held_moves_outside_0_1_is_one_line_naming_the_flag_and_nothing_is_written(tmp_path):
    root = tmp_path / "data"
    result = run_in_process(
        "lerobot-iupe-collect", "--env.type=metaworld_state", TASK, "--env.play_held_moves=1.5", "--agent=play",
        "--episodes=1", "--dataset.repo_id=local/x", f"--dataset.root={root}",
    )  # fmt: skip
    assert result.returncode == 2 and "Traceback" not in result.stderr
    line = result.stderr.strip().splitlines()[-1]
    assert "--env.play_held_moves" in line and "[0, 1]" in line and "1.5" in line
    assert not root.exists()


def test_the_env_names_a_wrong_task_for_lerobot_eval_too():
    from lerobot_iupe.envs.metaworld import MetaWorldStateEnv

    with pytest.raises(ValueError, match="--env.task: 'metaworld-push-v2' is not a Meta-World task"):
        MetaWorldStateEnv(task="metaworld-push-v2")


def test_object_moves_carry_the_object_with_the_gripper_closed_and_hand_only_play_never_does():
    """``--env.play_object_moves``: play grasps pick-place's puck and lifts it with the gripper closed, which the
    hand-only play of the same episodes never does."""

    def lifted_steps(object_moves: float) -> int:
        env = MetaWorldStateEnvConfig(task="pick-place-v3", play_object_moves=object_moves).make()
        play, lifted = make_agent("metaworld_state", "play"), 0
        for seed in (0, 1):
            observation, _ = env.reset(seed=seed)
            table = observation["environment_state"][6]
            for _ in range(400):
                action = play(env, observation)
                observation, _, terminated, truncated, _ = env.step(action)
                lifted += bool(observation["environment_state"][6] > table + 0.02 and action[3] > 0)
                if terminated or truncated:
                    break
        env.close()
        return lifted

    assert lifted_steps(0.5) > 50 and lifted_steps(0.0) == 0
    with pytest.raises(ValueError, match="--env.play_object_moves"):
        MetaWorldStateEnvConfig(task="reach-v3", play_object_moves=-0.1).validate()
