"""Goal-agnostic play pre-demonstrations (``--agent=play``) for SO-101, where uniform random actions never carry
the arm to where the expert works."""

import numpy as np
from conftest import collect, run_in_process
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION

from lerobot_iupe.envs.so101 import PLAY_HIGH, PLAY_LOW, SO101PickPlaceEnv
from lerobot_iupe.experts import make_agent


def grasp_points(agent: str, seed: int, steps: int, move_block_to: tuple[float, float] | None = None):
    env = SO101PickPlaceEnv()
    observation, _ = env.reset(seed=seed)
    if move_block_to is not None:  # far from where play reaches; the goal marker moves too (it is not physical)
        sim = env.env.unwrapped
        sim._data.jnt("block").qpos[:2] = move_block_to
        sim._goal_pos[:2] = (0.1, -0.18)
    act = make_agent("so101_pickplace", agent)
    points, actions = [], []
    for _ in range(steps):
        action = act(env, observation)
        observation, *_ = env.step(action)
        actions.append(action)
        points.append(np.asarray(env.env.unwrapped.ik_point_pos).copy())
    env.close()
    return np.array(points), np.array(actions)


def test_play_never_reads_the_block_or_the_goal():
    _, actions = grasp_points("play", seed=3, steps=40)
    _, moved = grasp_points("play", seed=3, steps=40, move_block_to=(0.38, 0.18))
    np.testing.assert_array_equal(actions, moved)


def test_play_reaches_the_table_where_blocks_lie_and_uniform_random_does_not():
    play, actions = grasp_points("play", seed=0, steps=150)
    random, _ = grasp_points("random", seed=0, steps=150)
    near_table = lambda p: (p[:, 2] < PLAY_LOW[2] + 0.03) & (p[:, 0] > 0.15) & (p[:, 0] < 0.30)  # noqa: E731
    assert near_table(play).sum() >= 5  # where the expert grasps and releases
    assert not near_table(random).any()
    assert np.ptp(play[:, 1]) > 0.5 * (PLAY_HIGH[1] - PLAY_LOW[1])  # it travels across the box
    assert {0.0, 1.0} <= set(np.round(actions[:, 3], 6))  # and both opens and closes the gripper


def test_collect_play_keeps_actions_and_is_refused_for_envs_without_a_play_agent(data_dir):
    root = collect(
        data_dir, "so101-play", "--env.type=so101_pickplace", "--env.episode_length=20", "--agent=play",
        "--episodes=2", "--seed=1000",
    )  # fmt: skip
    dataset = LeRobotDataset("local/so101-play", root=root)
    assert dataset.meta.features[ACTION]["shape"] == (4,) and dataset.num_episodes == 2
    refused = run_in_process(
        "lerobot-iupe-collect", "--env.type=cartpole", "--agent=play", "--episodes=1",
        "--dataset.repo_id=local/cartpole-play", f"--dataset.root={data_dir / 'cartpole-play'}",
    )  # fmt: skip
    assert refused.returncode != 0 and "--agent=play" in refused.stderr + refused.stdout
    assert not (data_dir / "cartpole-play").exists()


def test_play_is_seeded():
    _, first = grasp_points("play", seed=5, steps=20)
    _, again = grasp_points("play", seed=5, steps=20)
    np.testing.assert_array_equal(first, again)
