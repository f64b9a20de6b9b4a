import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from lerobot.envs.factory import make_env

from lerobot_iupe.collect import dataset_features
from lerobot_iupe.envs import (
    HELDOUT_LAYOUT_START,
    AcrobotEnvConfig,
    CartPoleEnvConfig,
    MazeEnvConfig,
    MazeLayout,
    MountainCarEnvConfig,
)
from lerobot_iupe.envs.configs import (
    LunarLanderEnvConfig,
    SO101PickPlaceEnvConfig,
    env_config_from_settings,
    env_settings,
)
from lerobot_iupe.envs.rollout import agent_act, run_episodes
from lerobot_iupe.experts import make_agent

CONFIGS = [
    CartPoleEnvConfig(),
    AcrobotEnvConfig(),
    MountainCarEnvConfig(),
    MazeEnvConfig(size=3),
    MazeEnvConfig(size=10),
    LunarLanderEnvConfig(),
    SO101PickPlaceEnvConfig(),
    SO101PickPlaceEnvConfig(relative_positions=True),
]


def config_id(cfg) -> str:
    return cfg.type + ("-relative" if getattr(cfg, "relative_positions", False) else "")


@pytest.mark.parametrize("cfg", CONFIGS, ids=config_id)
def test_env_passes_gymnasium_checker(cfg):
    env = gym.make(cfg.gym_id, **cfg.gym_kwargs).env.env  # below TimeLimit/OrderEnforcing: our own class
    check_env(env)


@pytest.mark.parametrize("cfg", CONFIGS, ids=config_id)
def test_lerobot_make_env_steps_with_float_actions(cfg):
    envs = make_env(cfg, n_envs=2)
    vec = envs[cfg.type][0]
    obs, info = vec.reset(seed=[0, 1])
    for key in cfg.observation_keys:
        assert obs[key].shape == (2, *cfg.features[key].shape)
    action_dim = cfg.features["action"].shape[0]
    obs, reward, terminated, truncated, info = vec.step(np.zeros((2, action_dim), dtype=np.float32))
    assert reward.shape == (2,)
    assert vec.call("_max_episode_steps")[0] == cfg.max_episode_steps
    assert isinstance(vec.call("task_description")[0], str)
    vec.close()


def test_state_only_so101_renders_lerobot_eval_videos_headless_at_the_fast_quality():
    """lerobot-eval renders every env for its videos, cameras or not: the state-only arm renders offscreen too,
    without the multisampling and shadows that made each frame cost 0.7 s on a CPU."""
    vec = make_env(SO101PickPlaceEnvConfig(relative_positions=True), n_envs=1)["so101_pickplace"][0]
    vec.reset(seed=[0])
    env = vec.envs[0].unwrapped
    frame = vec.envs[0].render()
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8 and frame.std() > 0
    assert env._model.vis.quality.offsamples == 0 and not env._model.light_castshadow.any()
    vec.close()


@pytest.mark.parametrize(
    ("cfg", "shape"),
    [
        (CartPoleEnvConfig(), (200, 300, 3)),
        (AcrobotEnvConfig(), (250, 250, 3)),
        (MountainCarEnvConfig(), (200, 300, 3)),
        (LunarLanderEnvConfig(), (200, 300, 3)),
    ],
    ids=lambda value: getattr(value, "type", ""),
)
def test_gymnasium_envs_render_lerobot_eval_videos_at_half_size_with_their_thin_lines(cfg, shape):
    """lerobot-eval keeps a batch's every frame in memory: at gymnasium's full size the README's CartPole evaluation
    peaked at 8.9 GB. Half size, area-averaged: the 1-pixel track and ground lines are still drawn."""
    vec = make_env(cfg, n_envs=1)[cfg.type][0]
    vec.reset(seed=[0])
    frame = vec.envs[0].render()
    assert frame.shape == shape and frame.dtype == np.uint8
    # CartPole's track, Acrobot's goal line and MountainCar's hill are 1-pixel lines across the whole frame,
    # LunarLander's ground under its sky too: every column holds a dark and a light pixel
    contrast = frame.max(axis=(0, 2)).astype(int) - frame.min(axis=(0, 2))
    assert (contrast > 40).mean() > 0.95
    vec.close()


def test_bad_action_is_refused():
    env = CartPoleEnvConfig().make()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="not a valid action id"):
        env.step(np.array([2.0]))


def test_maze_layout_is_deterministic_and_perfect_plus_loops():
    a, b = MazeLayout.generate(5, 7), MazeLayout.generate(5, 7)
    assert np.array_equal(a.open, b.open)
    assert not np.array_equal(a.open, MazeLayout.generate(5, 8).open)
    openings = a.open.sum() // 2
    assert openings == 5 * 5 - 1 + round(0.1 * 25)  # spanning tree + extra openings (loops)
    assert (a.shortest_path_actions((4, 4))[np.arange(5)[:, None], np.arange(5)] >= 0).sum() == 24  # all reach goal


def test_maze_size_below_two_is_refused():
    with pytest.raises(ValueError, match="--env.size must be at least 2"):
        MazeEnvConfig(size=1).validate()


def test_maze_rules():
    env = MazeEnvConfig(size=3).make()
    obs, info = env.reset(seed=0, options={"layout_id": 4})
    layout = env.unwrapped.layout
    blocked = next(a for a in range(4) if not layout.open[0, 0, a])
    obs2, reward, terminated, truncated, info = env.step(blocked)
    assert info["agent_cell"] == (0, 0) and np.array_equal(obs2["pixels"], obs["pixels"])
    assert reward == pytest.approx(-0.1 / 9) and not terminated
    total, done, steps = reward, False, 1
    while not done:
        obs, reward, terminated, truncated, info = env.step(env.unwrapped.expert_action())
        total += reward
        steps += 1
        done = terminated or truncated
    assert terminated and info["is_success"] and reward == 1.0
    assert total == pytest.approx(1.0 + (steps - 1) * -0.1 / 9)  # +1 at the goal, the step penalty otherwise


def test_maze_layout_ranges():
    demo = MazeEnvConfig(size=3, num_layouts=10).make()
    heldout = MazeEnvConfig(size=3, layouts="heldout", num_layouts=10).make()
    demo_ids = {demo.reset(seed=s)[1]["layout_id"] for s in range(30)}
    heldout_ids = {heldout.reset(seed=s)[1]["layout_id"] for s in range(30)}
    assert demo_ids <= set(range(10))
    assert heldout_ids <= set(range(HELDOUT_LAYOUT_START, HELDOUT_LAYOUT_START + 10))


@pytest.mark.parametrize(("size", "distinct", "shared"), [(3, 35, 88), (5, 100, 0)])
def test_held_out_layouts_are_new_mazes_except_at_3x3(size, distinct, shared):
    """The README's statement: 3×3 has too few mazes for 100 distinct layouts; 5×5 held-out mazes are all new."""
    demo = {MazeLayout.generate(size, i).block_image().tobytes() for i in range(100)}
    heldout = [MazeLayout.generate(size, HELDOUT_LAYOUT_START + i).block_image().tobytes() for i in range(100)]
    assert len(demo) == distinct
    assert sum(layout in demo for layout in heldout) == shared


def test_cartpole_success_is_the_papers_goal():
    from lerobot_iupe.experts import cartpole_expert

    env = CartPoleEnvConfig().make()
    obs, _ = env.reset(seed=0)
    for step in range(1, 200):
        obs, _, _, _, info = env.step(cartpole_expert(env, obs))
        assert info["is_success"] == (step >= 195)


def test_consecutive_seeds_play_distinct_layouts():
    """LeRobot's evaluation seeds its envs with consecutive seeds: 100 episodes must be 100 different mazes."""
    for layouts in ("demo", "heldout"):
        env = MazeEnvConfig(size=5, layouts=layouts).make()
        ids = [env.reset(seed=500_000 + i)[1]["layout_id"] for i in range(100)]
        assert len(set(ids)) == 100


@pytest.mark.parametrize("cfg", [LunarLanderEnvConfig(), SO101PickPlaceEnvConfig()], ids=lambda c: c.type)
def test_continuous_env_experts_succeed_and_random_agents_fail(cfg):
    env = cfg.make()
    for agent, expected in (("expert", True), ("random", False)):
        act = agent_act([env], make_agent(cfg.type, agent))
        for seed in (100, 101, 102):
            episode = run_episodes([env], act, [seed])[0]
            assert episode.success == expected
            assert all(np.asarray(a).shape == cfg.features["action"].shape for a in episode.actions)
    env.close()


def test_lunarlander_success_is_a_safe_landing_on_the_pad():
    env = LunarLanderEnvConfig().make()
    env.reset(seed=3)
    for _ in range(1000):  # engines off: the lander falls and crashes, terminated but not a landing
        _, _, terminated, truncated, info = env.step(np.array([-1.0, 0.0], dtype=np.float32))
        if terminated or truncated:
            break
    assert terminated and not info["is_success"]
    env.reset(seed=3)
    expert = (
        env.unwrapped.expert_action
        if hasattr(env.unwrapped, "expert_action")
        else env.get_wrapper_attr("expert_action")
    )
    successes = []
    for _ in range(1000):  # gymnasium's heuristic lands on the pad: a success, and only once at rest
        _, _, terminated, truncated, info = env.step(expert())
        successes.append(info["is_success"])
        if terminated or truncated:
            break
    assert terminated and successes[-1] and not any(successes[:-1])


def test_lunarlander_goal_is_standing_on_the_pad_at_any_step_which_rest_is_not_required_for():
    env = LunarLanderEnvConfig().make()
    expert = make_agent("lunarlander", "expert")
    falling = run_episodes([env], lambda observations, active: [np.array([-1.0, 0.0], dtype=np.float32)], [3])[0]
    assert not falling.goal_reached and not falling.success  # engines off: a crash is not the goal

    landed = run_episodes([env], agent_act([env], expert), [3])[0]
    first_goal = landed.goals.index(True)
    assert landed.success and landed.goal_reached and first_goal < len(landed) - 1  # on the pad before at rest

    steps = iter(range(10_000))

    def stand_then_take_off(observations, active):  # the same landing until it stands on the pad, then full throttle
        standing = next(steps) > first_goal
        return [np.array([1.0, 0.0], dtype=np.float32) if standing else expert(env, observations[0])]

    hopper = run_episodes([env], stand_then_take_off, [3])[0]
    assert hopper.goal_reached and not hopper.success


def test_so101_success_is_the_plugins_succeed_flag():
    env = SO101PickPlaceEnvConfig().make()
    env.reset(seed=0)
    flags = []
    for _ in range(100):
        _, _, terminated, truncated, info = env.step(env.get_wrapper_attr("expert_action")())
        flags.append((info["succeed"], info["is_success"]))
        if terminated or truncated:
            break
    assert flags[-1] == (True, True) and all(succeed == success for succeed, success in flags)


def test_env_settings_rebuild_any_lerobot_env_type():
    from lerobot_env_so101.configuration_so101 import SO101Env

    plugin = SO101Env(action_scale=0.5, episode_length=40)  # a lerobot_env_* plugin's own type
    rebuilt = env_config_from_settings(env_settings(plugin))
    assert (type(rebuilt), rebuilt.action_scale, rebuilt.episode_length) == (SO101Env, 0.5, 40)
    ours = env_config_from_settings(env_settings(SO101PickPlaceEnvConfig(action_scale=0.05)))
    assert ours.action_scale == 0.05 and ours.type == "so101_pickplace"


@pytest.mark.parametrize("cfg", [c for c in CONFIGS if not c.is_image], ids=config_id)
def test_datasets_name_every_state_entry(cfg):
    features = dataset_features(cfg, with_actions=True)
    for key in ("observation.state", "observation.environment_state"):
        if key in features:
            names = features[key]["names"]
            assert len(set(names)) == len(names) == features[key]["shape"][0]
            assert all("." in name for name in names)  # LeRobot's "<part>.<quantity>", never a bare index


@pytest.mark.parametrize("relative", [False, True], ids=["absolute", "relative_positions"])
def test_so101_state_names_say_what_each_entry_is(relative):
    cfg = SO101PickPlaceEnvConfig(relative_positions=relative)
    env = cfg.make()
    obs, _ = env.reset(seed=3)
    for _ in range(5):
        obs, *_ = env.step(np.array([0.5, -0.3, -0.4, 0.2], dtype=np.float32))
    sim = env.unwrapped
    state = dict(zip(cfg.state_names("agent_pos"), obs["agent_pos"], strict=True))
    world = dict(zip(cfg.state_names("environment_state"), obs["environment_state"], strict=True))
    for joint in ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll"):
        assert state[f"{joint}.pos"] == pytest.approx(sim.data.joint(joint).qpos[0], abs=1e-6)
        assert state[f"{joint}.vel"] == pytest.approx(sim.data.joint(joint).qvel[0], abs=1e-6)
    ee, block = sim.data.sensor("so101/ee_pos").data, sim.data.sensor("block_pos").data
    assert [state[f"ee.{a}"] for a in "xyz"] == pytest.approx(list(ee), abs=1e-6)
    assert [world[f"block.{a}"] for a in "xyz"] == pytest.approx(list(block), abs=1e-6)
    assert [world[f"goal.{a}"] for a in "xyz"] == pytest.approx(list(sim.goal_pos), abs=1e-6)
    assert -1 <= state["gripper.pos"] <= 1
    assert env.observation_space["environment_state"].shape == (12 if relative else 6,)
    assert cfg.features["environment_state"].shape == (12 if relative else 6,)
    if relative:  # the block and the goal seen from the end effector
        assert [world[f"block_from_ee.{a}"] for a in "xyz"] == pytest.approx(list(block - ee), abs=1e-6)
        assert [world[f"goal_from_ee.{a}"] for a in "xyz"] == pytest.approx(list(sim.goal_pos - ee), abs=1e-6)
        settings = env_settings(cfg)
        assert settings["relative_positions"] is True
        assert env_config_from_settings(settings).features["environment_state"].shape == (12,)
    else:  # settings recorded before the option existed rebuild the same env
        assert "relative_positions" not in env_settings(cfg)
    env.close()
