"""The linear-first IDM (policy/joint_idm.py): its pure parts against their definitions, the generator's arms, and
the whole path — lerobot-train with default flags on two labelled episodes (an SO-101 follower with a 4-frame
transport delay; an SO-101 leader driving another 7-value follower; a humanoid whose left arm is idle in the labelled
episodes), then lerobot-iupe-relabel --dry_run=true on held-out episodes — against a ridge regression and the copy
on the same data."""

from __future__ import annotations

import contextlib
import io
import json
import re
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, once, run_in_process, train_once

from lerobot_iupe.data.arm_recording import (
    ENCODER_STEP,
    HUMANOID,
    HUMANOID_LEFT_ARM,
    OTHER_LEADER,
    SO101_MISCALIBRATED,
    ArmDynamics,
    gravity_offset,
    teleoperated_episode,
)
from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.policy import IUPEPolicy
from lerobot_iupe.policy.action_sources import (
    action_sources,
    best_copy_lag,
    idle_dimensions,
    is_rate_name,
    max_lag,
    named_sources,
    rows_within,
    stem_sources,
)
from lerobot_iupe.policy.joint_idm import (
    BLOCKS,
    copy_map,
    episode_blocks,
    fit_linear,
    fit_ridge,
    fold_sums,
    gate_weights,
    selection_folds,
    solve_ridge,
)

DELAY = 4


def test_joint_columns_pair_each_action_with_the_state_of_its_name():
    state = ["shoulder_pan.pos", "elbow_flex.pos", "gripper.pos"]
    assert named_sources(["gripper.pos", "shoulder_pan.pos"], state) == [2, 0]
    assert named_sources(["gripper.pos", "dx"], state) == [2, None]  # not every action is a joint position
    assert named_sources(["main_engine", "lateral_engines"], ["x", "y"]) == [None, None]


def test_the_lag_is_where_the_action_best_matches_a_later_state_within_its_episode():
    rng = np.random.default_rng(0)
    walk = rng.normal(size=(400, 2)).cumsum(axis=0)
    actions = np.roll(walk, -3, axis=0)  # a_t = s_{t+3}
    episodes = np.repeat([0, 1], 200)
    # The last frames of each episode would pair across the boundary; they must not count.
    assert best_copy_lag(walk, actions, episodes, [0, 1]) == 3
    assert best_copy_lag(walk, walk, episodes, [0, 1]) == 0


def test_each_action_gets_its_own_lag_and_a_differently_named_one_the_column_it_follows():
    rng = np.random.default_rng(5)
    walk = rng.normal(size=(600, 3)).cumsum(axis=0)
    episodes = np.repeat([0, 1, 2], 200)
    actions = np.stack([np.roll(walk[:, 0], -2), np.roll(walk[:, 1], -7), -3.0 * np.roll(walk[:, 2], -4) + 9], 1)
    # Two actions named as states 0 and 1, the third named otherwise: it follows state 2 at lag 4, sign and scale aside.
    columns, lags, kinds = action_sources(walk, actions, episodes, [0, 1, None])
    assert columns == [0, 1, 2] and lags == [2, 7, 4] and kinds == ["position"] * 3
    # Actions that follow no state (an engine's thrust) are not the linear-first model's; one such dimension beside a
    # majority that do is, with its closest column.
    noise = rng.normal(size=(600, 1))
    assert action_sources(walk, noise, episodes, [None]) is None
    assert (
        action_sources(walk, np.concatenate([actions[:, :2], noise, noise], axis=1), episodes, [0, 1, None, None])
        is None
    )
    columns, _, _ = action_sources(walk, np.concatenate([actions, noise], axis=1), episodes, [0, 1, None, None])
    assert columns[:3] == [0, 1, 2] and len(columns) == 4
    # With cameras, a dimension that follows no column is read off them, at lag 0; all of them: no linear model.
    _, lags, kinds = action_sources(walk, np.concatenate([actions, noise], axis=1), episodes, [0, 1, None, None],
                                    cameras=True)  # fmt: skip
    assert kinds == ["position"] * 3 + ["camera"] and lags[3] == 0
    assert action_sources(walk, noise, episodes, [None], cameras=True) is None
    assert named_sources(["a", "b"], ["b", "c"]) == [None, 0]
    # Candidate fits are judged on whole held-out episodes where there are two or more, on blocks in one.
    assert selection_folds(episodes).tolist() == np.repeat([0, 1, 2], 200).tolist()
    assert len(np.unique(selection_folds(np.zeros(100, dtype=int)))) == BLOCKS


def test_a_velocity_or_delta_takes_the_difference_of_its_column_at_its_own_lag_sign_and_gain():
    rng = np.random.default_rng(7)
    walk = rng.normal(size=(600, 3)).cumsum(axis=0)
    episodes = np.repeat([0, 1, 2], 200)
    step = np.diff(walk, axis=0, append=walk[-1:])  # step[t] = s_{t+1} - s_t
    # a_0 = 10·(s_{t+1} − s_t) (a velocity at 10 fps), a_1 = −2·(s_{t+3} − s_{t+2}) + 1 (a delta, sign and lag), a_2 =
    # the difference that ends at t (a velocity measured up to t): each named by stem, or not named at all.
    actions = np.stack([10 * step[:, 0], -2 * np.roll(step[:, 1], -2) + 1, np.roll(step[:, 2], 1)], axis=1)
    inside = rows_within(episodes, (-1, 3))
    names, state = ["joint_a_vel", "joint_b.delta", "c_dot"], ["joint_a", "joint_b.pos", "c"]
    stems = stem_sources(names, state)
    assert stems == [0, 1, 2] and [is_rate_name(n) for n in names] == [True, True, True]
    for given in (stems, None):
        columns, lags, kinds = action_sources(walk[inside], actions[inside], episodes[inside], [None] * 3, 10, given,
                                              lowest=-1)  # fmt: skip
        assert columns == [0, 1, 2] and lags == [0, 2, -1] and kinds == ["difference"] * 3
    offsets = list(range(-1, 12))
    window = walk[np.clip(inside[:, None] + np.asarray(offsets), 0, len(walk) - 1)]
    flat = window.reshape(len(inside), -1)
    copy = copy_map(flat, actions[inside], 3, offsets, ([0, 1, 2], [0, 2, -1], ["difference"] * 3), [False] * 3)
    at = lambda offset, column: copy[offsets.index(offset) * 3 + column, column]  # noqa: E731
    assert at(1, 0) == pytest.approx(10) and at(0, 0) == pytest.approx(-10)  # gain 10 on s_{t+1} − s_t
    assert np.count_nonzero(copy[:, 0]) == 2
    assert at(3, 1) == pytest.approx(-2) and at(2, 1) == pytest.approx(2)
    assert at(0, 2) == pytest.approx(1) and at(-1, 2) == pytest.approx(-1)


def test_an_idle_difference_borrows_the_others_filter_and_gain():
    rng = np.random.default_rng(3)
    walk = rng.normal(size=(600, 4)).cumsum(axis=0)
    walk[:, 3] = 5.0 + rng.normal(0, 1e-3, 600)  # the fourth joint rests in the labelled episodes
    episodes = np.repeat([0, 1, 2], 200)
    step = np.diff(walk, axis=0, append=walk[-1:])
    actions = 10 * step + rng.normal(0, 0.01, step.shape)
    inside = rows_within(episodes, (0, 1))
    assert idle_dimensions(actions[inside]).tolist() == [False, False, False, True]
    sources = action_sources(walk[inside], actions[inside], episodes[inside], [None] * 4, 10, [0, 1, 2, 3],
                             [True] * 4)  # fmt: skip
    assert sources[0] == [0, 1, 2, 3] and sources[2] == ["difference"] * 4 and sources[1][3] == 0
    offsets = list(range(0, 12))
    windows = walk[np.clip(inside[:, None] + np.asarray(offsets), 0, len(walk) - 1)]
    weight, bias, report = fit_linear(windows, actions[inside], episodes[inside], offsets, sources, [False] * 4)
    assert report["fit"][3] == "borrowed"  # the others' filter, not a fit to its own noise
    own = np.arange(len(offsets)) * 4 + 3
    assert abs(weight[own, 3].sum()) < 1e-9  # differences only: its resting pose sends no label anywhere
    # A new episode moves it: labelled as 10·(s_{t+1} − s_t), the others' gain, not by a fit to its noise.
    moving = rng.normal(size=(50, 4)).cumsum(axis=0)
    new_windows = moving[np.clip(np.arange(50)[:, None] + np.asarray(offsets), 0, 49)].reshape(50, -1)
    predicted = new_windows @ weight + bias
    true = 10 * np.diff(moving[:, 3], append=moving[-1, 3])
    assert r2(predicted[:-1, [3]], true[:-1, None])[0] > 0.99


def windows_of(states: np.ndarray, offsets: list[int], length: int) -> np.ndarray:
    """Windows (N, F, D) at ``offsets`` of episodes of ``length`` frames, clamped into each episode."""
    rows = np.arange(len(states))
    first = rows // length * length
    return states[np.clip(rows[:, None] + np.asarray(offsets), first[:, None], first[:, None] + length - 1)]


def generated(body, episodes: int, seed: int, idle=()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    parts = [
        teleoperated_episode(300, np.random.default_rng(seed + i), ArmDynamics(), body, idle) for i in range(episodes)
    ]
    states, actions = (np.concatenate([p[n] for p in parts]).astype(np.float64) for n in (0, 1))
    return states, actions, np.repeat(np.arange(episodes), 300)


def r2(predicted: np.ndarray, true: np.ndarray) -> np.ndarray:
    return 1.0 - ((predicted - true) ** 2).mean(axis=0) / true.var(axis=0)


def test_a_joint_idle_in_the_labelled_episodes_follows_its_own_state_on_episodes_where_it_moves():
    states, actions, episodes = generated(HUMANOID, 2, 0, idle=HUMANOID_LEFT_ARM)
    moving_states, moving_actions, _ = generated(HUMANOID, 3, 500)
    idle = [HUMANOID.action_names.index(name) for name in HUMANOID_LEFT_ARM]
    within = max(actions[episodes == e][:, idle].std(axis=0).max() for e in (0, 1))
    assert within < 0.05 * moving_actions[:, idle].std(axis=0).min()  # barely moves in the labelled episodes
    named = list(range(26))
    sources = action_sources(states, actions, episodes, named, max_lag(30))
    columns, lags, _ = sources
    hands = [j for j, name in enumerate(HUMANOID.action_names) if name.split("_", 1)[1] in ("index", "middle")]
    assert min(lags[j] for j in hands) > max(lags[j] for j in range(14))  # the fingers answer later than the arms
    offsets = list(range(-1, max_lag(30) + 1))
    weight, bias, report = fit_linear(
        windows_of(states, offsets, 300), actions, episodes, offsets, sources, [True] * 26
    )
    predicted = windows_of(moving_states, offsets, 300).reshape(len(moving_states), -1) @ weight + bias
    rows = np.arange(len(moving_states))
    for j in idle:
        copied = moving_states[np.minimum(rows + lags[j], rows // 300 * 300 + 299), j]
        assert r2(predicted[:, j], moving_actions[:, j]) >= r2(copied, moving_actions[:, j]) - 0.002, (
            HUMANOID.action_names[j],
            report["fit"][j],
        )


def test_a_leader_of_another_arm_takes_the_fit_over_every_column_where_its_map_mixes_them():
    states, actions, episodes = generated(OTHER_LEADER, 3, 0)
    named = named_sources(list(OTHER_LEADER.action_names), list(OTHER_LEADER.state_names))
    assert named == [None] * 5 + [6]  # only the grippers share a name
    sources = action_sources(states, actions, episodes, named, max_lag(30))
    assert sources[0] == [0, 1, 2, 4, 5, 6]  # joint_4, held near 0, is no action's source
    offsets = list(range(-1, max_lag(30) + 1))
    _, _, report = fit_linear(
        windows_of(states, offsets, 300), actions, episodes, offsets, sources, [n is not None for n in named]
    )
    assert report["fit"][1] == "all"  # shoulder_lift drives joint_2 together with elbow_flex
    assert report["fit"][0] == "own"  # shoulder_pan is joint_1, sign aside


def object_and_sensor_episodes(episodes: int, seed: int, sensor_spread: float, length: int = 200) -> tuple:
    """A hand (column 0) whose commanded delta a_t = 10·(s_{t+1} − s_t) + 3·object_t + e_t, an object (column 1) that
    shows part of it, a third column that moves, and a sensor (column 2) at ``sensor_spread`` × e_t: barely moving,
    yet in the labelled episodes it follows what no other column shows (Meta-World peg-insert-side's peg tilt)."""
    rng = np.random.default_rng(seed)
    states, actions = [], []
    for _ in range(episodes):
        walks = np.cumsum(rng.normal(0.0, 0.05, size=(length + 1, 4)), axis=0)
        noise = rng.normal(0.0, 0.3, size=length + 1)
        walks[:, 2] = sensor_spread * noise if sensor_spread < 1e-3 else rng.normal(0.0, sensor_spread, length + 1)
        states.append(walks[:length])
        actions.append(10.0 * (walks[1:, 0] - walks[:-1, 0]) + 3.0 * walks[:-1, 1] + noise[:length])
    return np.concatenate(states), np.concatenate(actions)[:, None], np.repeat(np.arange(episodes), length)


def test_a_column_idle_in_the_labelled_episodes_is_not_read_where_a_new_episode_moves_it():
    offsets = list(range(-1, 4))
    states, actions, episodes = object_and_sensor_episodes(4, 0, sensor_spread=1e-5)
    sources = ([0], [0], ["difference"])
    weight, bias, report = fit_linear(windows_of(states, offsets, 200), actions, episodes, offsets, sources, [False])
    assert report["fit"] == ["all"]  # the object's column explains what the hand's own window does not
    assert not weight[[f * 4 + 2 for f in range(len(offsets))], 0].any()  # the idle sensor has no weight
    moved, new_actions, _ = object_and_sensor_episodes(3, 50, sensor_spread=0.05)  # the sensor moves, unrelated
    predicted = windows_of(moved, offsets, 200).reshape(len(moved), -1) @ weight + bias
    assert r2(predicted, new_actions)[0] > 0.9  # all but e (about 3 % of the variance); reading the sensor: −7.8e6


def test_a_camera_dimensions_linear_part_is_its_labelled_mean_whatever_the_state_does_later():
    states, actions, episodes = generated(OTHER_LEADER, 2, 0)
    sources = ([0, 1, 2, 4, 5, 6], [2] * 6, ["position"] * 5 + ["camera"])
    offsets = list(range(-1, max_lag(30) + 1))
    weight, bias, report = fit_linear(
        windows_of(states, offsets, 300), actions, episodes, offsets, sources, [False] * 5 + [True]
    )
    assert report["fit"][5] == "mean" and not weight[:, 5].any()
    assert bias[5] == pytest.approx(actions[:, 5].mean())  # a pose never labelled cannot send it anywhere


def test_ridge_recovers_a_linear_map_and_chooses_each_targets_strength_by_held_out_episodes():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 5))
    exact = x @ rng.normal(size=(5, 2)) + 3.0
    noise = rng.normal(size=(300, 1))  # a target no feature explains
    weight, bias, alphas, _ = fit_ridge(x, np.concatenate([exact, noise], axis=1), np.repeat([0, 1, 2], 100))
    assert np.abs(x @ weight[:, :2] + bias[:2] - exact).max() < 0.05
    assert alphas[0] <= 0.1 and alphas[1] <= 0.1  # exact data: the weakest penalty wins
    assert alphas[2] >= 100.0  # noise: the strongest, whatever the other targets chose
    # Folds are contiguous blocks of each episode, BLOCKS to an episode.
    blocks = episode_blocks(np.array([7] * 2 * BLOCKS + [3] * BLOCKS))
    assert blocks.tolist() == [BLOCKS + n // 2 for n in range(2 * BLOCKS)] + list(range(BLOCKS))


def test_a_ridge_over_some_columns_solved_from_sums_over_more_is_the_ridge_fitted_on_those_columns_alone():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(400, 6)) * rng.uniform(0.1, 5.0, size=6)
    y = x @ rng.normal(size=(6, 2)) + rng.normal(size=(400, 2))
    folds = selection_folds(np.repeat(np.arange(4), 100))
    sums = fold_sums(x, y, folds)
    for columns, target in (([0, 2, 5], 0), ([1, 3], 1), (list(range(6)), 1)):
        alone = fit_ridge(x[:, columns], y[:, [target]], None, folds=folds)
        from_sums = solve_ridge(sums, columns=columns, targets=[target])
        for a, b in zip(alone, from_sums, strict=True):
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12)


def test_the_gate_keeps_what_the_network_gets_right_and_drops_what_it_gets_wrong():
    rng = np.random.default_rng(2)
    residual = rng.normal(size=(100, 3))
    correction = np.stack([residual[:, 0], -residual[:, 1], 2.0 * residual[:, 2]], axis=1)
    np.testing.assert_allclose(gate_weights(residual, correction), [1.0, 0.0, 0.5], atol=1e-9)


def test_the_generated_follower_lags_by_its_delay_stops_on_objects_and_reads_in_encoder_steps():
    rng = np.random.default_rng(3)
    lags = {}
    for delay in (2, 6):
        states, actions = teleoperated_episode(600, np.random.default_rng(4), ArmDynamics(delay=delay))
        lags[delay] = best_copy_lag(states, actions, np.zeros(600, dtype=int), list(range(6)))
    assert lags[6] - lags[2] == 4
    states, actions = teleoperated_episode(600, rng, ArmDynamics(grasp_probability=1.0))
    steps = states[:, :5] / ENCODER_STEP[:5]
    assert np.abs(steps - steps.round()).max() < 1e-3
    # The jaws rest on an object well above where the leader shut them.
    assert (states[DELAY + 2 :, 5] - actions[: -DELAY - 2, 5] > 8.0).mean() > 0.05


def test_the_generated_bodies_differ_from_the_so101_as_real_recordings_do():
    rng = np.random.default_rng(6)
    states, actions = teleoperated_episode(600, rng, body=OTHER_LEADER)
    assert states.shape == (600, 7) and actions.shape == (600, 6)
    assert states[:, 3].std() < 0.5  # joint_4 has no leader joint
    assert np.corrcoef(actions[:-4, 0], states[4:, 0])[0, 1] < -0.99  # a sign flipped
    states, actions = teleoperated_episode(600, rng, body=SO101_MISCALIBRATED)
    roll = 4
    assert abs((actions[:, roll] - states[:, roll]).mean()) > 50  # the leader reads far from the follower
    assert states[:, roll].std() < 0.2 * actions[:, roll].std()  # and the follower barely follows
    states, actions = teleoperated_episode(300, rng, body=HUMANOID, idle=HUMANOID_LEFT_ARM)
    assert states.shape == actions.shape == (300, 26) and np.abs(actions).max() < 3.0  # radians
    # An arm moved by hand (kinesthetic teaching): no delay, no lag, no sag, exact readings, so a_t = s_{t+1}.
    hand = ArmDynamics(delay=0, response=1.0, dead_band=0.0, gravity=(0.0, 0.0), grasp_probability=0.0,
                       quantise=False, reading_noise=0.0)  # fmt: skip
    states, actions = teleoperated_episode(100, rng, hand)
    np.testing.assert_allclose(states[1:], actions[:-1], atol=1e-4)


@pytest.fixture(scope="session")
def delayed_arm(data_dir):
    """Two labelled episodes and four held-out ones (with actions) of a follower with a 4-frame transport delay."""
    roots = {}
    for name, episodes, seed in (("arm-delay4", 2, 0), ("arm-delay4-held-out", 4, 100)):
        root = data_dir / name
        write = lambda root=root, n=episodes, s=seed, name=name: write_arm_recording(  # noqa: E731
            root, n, 300, seed=s, repo_id=f"local/{name}", dynamics=ArmDynamics(delay=DELAY), cameras=False
        )
        roots[name] = once(root, write, "meta/info.json")
    return roots["arm-delay4"], roots["arm-delay4-held-out"]


@pytest.fixture(scope="session")
def delayed_arm_run(delayed_arm, shared_dir):
    labelled, _ = delayed_arm
    return train_once(
        shared_dir / "runs" / "arm-delay4",
        "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{labelled.name}",
        f"--dataset.root={labelled}", "--batch_size=64", "--steps=400", "--save_freq=400", "--num_workers=0",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false",
        f"--output_dir={shared_dir / 'runs' / 'arm-delay4'}",
    )  # fmt: skip


def reference_table(stdout: str) -> dict[str, tuple[float, int, float, float]]:
    """{joint: (IDM, its lag, ridge, copy; NaN for none)} from the dry run's table."""
    rows = re.findall(
        r"^  (\S+)\s+(-?[\d.]+)\s+(-?\d+)\s+(-?[\d.]+)\s+(?:(-?[\d.]+) \(k=\d+\)|–)", stdout, re.MULTILINE
    )
    return {name: (float(idm), int(lag), float(ridge), float(copy or "nan")) for name, idm, lag, ridge, copy in rows}


def test_the_default_idm_of_a_delayed_arm_is_not_below_the_ridge_regression_on_any_joint(delayed_arm, delayed_arm_run):
    _, held_out = delayed_arm
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={delayed_arm_run / CHECKPOINT}", "--dataset.repo_id=local/x",
        f"--dataset.root={held_out}", "--dry_run=true", check=True,
    )  # fmt: skip
    table = reference_table(result.stdout)
    assert len(table) == 6, result.stdout
    for joint, (idm, _, ridge, _) in table.items():
        assert idm >= ridge - 0.005, f"{joint}: IDM {idm} vs ridge {ridge}\n{result.stdout}"
    assert "below the ridge regression" not in result.stdout


def test_the_window_reaches_past_the_delay_and_is_recorded_and_reloaded(delayed_arm_run):
    checkpoint = delayed_arm_run / CHECKPOINT
    config = json.loads((checkpoint / "config.json").read_text())
    assert config["joint_state_columns"] == list(range(6))
    lags = config["idm_joint_lags"]
    assert len(lags) == 6 and all(DELAY + 1 <= lag <= DELAY + 3 for lag in lags)  # the servo adds a frame or two
    assert config["idm_lag"] == max(lags)
    policy = IUPEPolicy.from_pretrained(checkpoint)
    assert policy.config.idm_joint_lags == lags and policy.config.idm_lag == config["idm_lag"]
    # The window reaches 0.35 s (11 frames at 30 fps) past t, and past every lag.
    assert max(policy.config.idm_window) == max(max_lag(30), config["idm_lag"] + 1 + config["idm_context"])
    assert bool(policy.idm_encoder.fitted)
    window = torch.randn(3, len(policy.config.idm_window), 6) * 30
    # The reloaded model labels a window as each joint's state at its lag plus corrections, not from scratch.
    with torch.no_grad():
        mean = policy.idm_head.mode(policy.eval().idm_window_output(window))
    copied = torch.stack([window[:, policy.config.idm_window.index(lag), j] for j, lag in enumerate(lags)], dim=1)
    assert (mean - copied).abs().mean() < (mean - window[:, 0]).abs().mean()
    # A checkpoint of the earlier arm model (one lag, no idm_joint_lags) is refused in words, not read wrongly.
    config.pop("idm_joint_lags")
    (tmp := checkpoint.parent / "earlier-arm-model").mkdir(exist_ok=True)
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "model.safetensors").write_bytes((checkpoint / "model.safetensors").read_bytes())
    with pytest.raises(ValueError, match="idm_joint_lags=None.*earlier version.*train it again"):
        IUPEPolicy.from_pretrained(tmp)


def generated_pair(data_dir, name: str, body, idle: tuple[str, ...] = ()) -> tuple:
    """Two labelled episodes (the ``idle`` leader joints still) and four held-out ones, with actions, of ``body``."""
    roots = []
    for part, episodes, seed, still in (("", 2, 0, idle), ("-held-out", 4, 100, ())):
        root = data_dir / f"{name}{part}"
        write = lambda root=root, n=episodes, s=seed, still=still: write_arm_recording(  # noqa: E731
            root, n, 300, seed=s, repo_id=f"local/{root.name}", cameras=False, body=body, idle=still
        )
        roots.append(once(root, write, "meta/info.json"))
    return tuple(roots)


def default_run_and_dry_run(shared_dir, labelled, held_out) -> tuple[dict, dict, str]:
    """lerobot-train with the defaults on ``labelled``, then the dry run's table on ``held_out``; and the config."""
    out = shared_dir / "runs" / labelled.name
    run = train_once(
        out, "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{labelled.name}",
        f"--dataset.root={labelled}", "--batch_size=64", "--steps=100", "--save_freq=100", "--num_workers=0",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", f"--output_dir={out}",
    )  # fmt: skip
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={run / CHECKPOINT}", "--dataset.repo_id=local/x",
        f"--dataset.root={held_out}", "--dry_run=true", check=True,
    )  # fmt: skip
    return reference_table(result.stdout), json.loads((run / CHECKPOINT / "config.json").read_text()), result.stdout


def test_a_leader_of_another_arm_is_labelled_no_worse_than_a_ridge_regression_on_any_joint(data_dir, shared_dir):
    labelled, held_out = generated_pair(data_dir, "other-leader", OTHER_LEADER)
    table, config, stdout = default_run_and_dry_run(shared_dir, labelled, held_out)
    # Every dimension has a difference copy: of the column of its name, else of the column the IDM follows.
    assert len(re.findall(r"^  \S+ .*\(d=\s*-?\d+\)", stdout, re.MULTILINE)) == 6, stdout
    assert len(table) == 6 and config["joint_state_columns"] == [0, 1, 2, 4, 5, 6]
    for joint, (idm, lag, ridge, copy) in table.items():
        assert idm >= ridge - 0.005, f"{joint}: IDM {idm} vs ridge {ridge}"
        assert np.isnan(copy) == (joint != "gripper.pos")  # a copy only where the names match
        assert lag == config["idm_joint_lags"][list(table).index(joint)]


def test_a_humanoid_arm_idle_in_the_labelled_episodes_is_labelled_no_worse_than_its_copy(data_dir, shared_dir):
    labelled, held_out = generated_pair(data_dir, "humanoid-idle-left", HUMANOID, idle=HUMANOID_LEFT_ARM)
    table, config, _ = default_run_and_dry_run(shared_dir, labelled, held_out)
    assert len(table) == 26
    for joint in HUMANOID_LEFT_ARM:
        idm, _, ridge, copy = table[joint]
        assert idm >= copy - 0.005, f"{joint}: IDM {idm} vs copy {copy}"
    lags = dict(zip(HUMANOID.action_names, config["idm_joint_lags"], strict=True))
    assert lags["right_index"] > lags["right_elbow"]  # the fingers' own, longer lag


def test_an_arm_idm_asked_of_an_unsupervised_run_or_of_cameras_is_refused_naming_the_flags():
    from lerobot_iupe.policy.configuration_iupe import IUPEConfig

    with pytest.raises(ValueError, match="joint_state_columns.*needs --policy.supervised=true"):
        IUPEConfig(joint_state_columns=[0, 1])
    with pytest.raises(ValueError, match="idm_observation_keys.*joint_state_columns=\\[\\]"):
        IUPEConfig(supervised=True, joint_state_columns=[0], idm_observation_keys=["observation.images.front"])
    from lerobot.configs.types import FeatureType, PolicyFeature

    features = {
        "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
        "observation.images.front": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 48, 64)),
    }
    camera_too = IUPEConfig(
        input_features=features, action_low=[-1.0, -1.0], action_high=[1.0, 1.0], supervised=True,
        joint_state_columns=[0, 1], idm_observation_keys=["observation.state", "observation.images.front"],
    )  # fmt: skip
    with pytest.raises(ValueError, match="linear-first IDM.*reads vectors only"):
        camera_too.validate_features()
    camera_too.idm_observation_keys = ["observation.state"]
    camera_too.validate_features()  # the same run reading the state alone is accepted
    assert IUPEConfig(supervised=True, joint_state_columns=[]).idm_window == [0, 1]


def test_the_generator_refuses_cameras_on_another_body_and_unknown_idle_joints_writing_nothing(tmp_path, monkeypatch):
    """scripts/make_arm_recording.py run in this process (its imports are already loaded): exit code 2, the flag
    named, no folder written."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "make_arm_recording.py"
    root = tmp_path / "arm"
    cases = [
        (["--body", "humanoid"], "--body=humanoid: the cameras draw an SO-101; add --no_cameras"),
        (["--body", "other_leader", "--no_cameras", "--idle", "left_elbow"], "--idle: ['left_elbow'] are not joints"),
    ]
    for flags, message in cases:
        monkeypatch.setattr(sys, "argv", [str(script), f"--root={root}", *flags])
        stderr = io.StringIO()
        with contextlib.redirect_stderr(stderr), pytest.raises(SystemExit) as exit_:
            runpy.run_path(str(script), run_name="__main__")
        assert exit_.value.code == 2 and message in stderr.getvalue(), stderr.getvalue()
        assert not root.exists()
    with pytest.raises(ValueError, match="idle joints \\['wrist'\\] are not among"):
        write_arm_recording(root, 1, 10, cameras=False, idle=("wrist",))
    assert not root.exists()


def test_wrist_gravity_sags_wrist_flex_by_the_whole_arms_pose():
    level, raised = np.zeros(6), np.array([0.0, 60.0, 0.0, 0.0, 0.0, 0.0])
    assert gravity_offset(level, (2.5, 4.0))[3] == 0.0  # off by default
    assert gravity_offset(level, (2.5, 4.0), 3.0)[3] == pytest.approx(-3.0)
    assert gravity_offset(raised, (2.5, 4.0), 3.0)[3] == pytest.approx(-1.5)  # the shoulder's angle moves it


def test_a_dimension_without_a_name_never_chooses_a_column_that_barely_moved():
    rng = np.random.default_rng(0)
    walks = np.cumsum(rng.normal(size=(600, 5)), axis=0)
    states = np.concatenate([walks[:, :4], 1e-3 * walks[:, 4:]], axis=1)  # the last column barely moves
    episodes = np.repeat([0, 1], 300)
    actions = np.stack([walks[:, 4], walks[:, 0]], axis=1)  # the first follows only the still column
    columns, _, kinds = action_sources(states, actions, episodes, [None, None], 10, cameras=True)
    assert columns[0] != 4 and kinds == ["camera", "position"], (columns, kinds)
