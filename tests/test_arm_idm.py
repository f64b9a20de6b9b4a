"""The arm IDM (policy/joint_idm.py): its pure parts against their definitions, the generator's follower, and the
whole path — lerobot-train with default flags on two labelled episodes of a follower with a 4-frame transport delay,
then lerobot-iupe-relabel --dry_run=true on held-out episodes — against a ridge regression on the same data."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, once, run_in_process, train_once

from lerobot_iupe.data.arm_recording import ENCODER_STEP, ArmDynamics, teleoperated_episode, write_arm_recording
from lerobot_iupe.policy import IUPEPolicy
from lerobot_iupe.policy.joint_idm import (
    BLOCKS,
    best_copy_lag,
    episode_blocks,
    fit_ridge,
    gate_weights,
    joint_state_columns,
)

DELAY = 4


def test_joint_columns_pair_each_action_with_the_state_of_its_name():
    state = ["shoulder_pan.pos", "elbow_flex.pos", "gripper.pos"]
    assert joint_state_columns(["gripper.pos", "shoulder_pan.pos"], state) == [2, 0]
    assert joint_state_columns(["gripper.pos", "dx"], state) is None  # not every action is a joint position
    assert joint_state_columns(["main_engine", "lateral_engines"], ["x", "y"]) is None


def test_the_lag_is_where_the_action_best_matches_a_later_state_within_its_episode():
    rng = np.random.default_rng(0)
    walk = rng.normal(size=(400, 2)).cumsum(axis=0)
    actions = np.roll(walk, -3, axis=0)  # a_t = s_{t+3}
    episodes = np.repeat([0, 1], 200)
    # The last frames of each episode would pair across the boundary; they must not count.
    assert best_copy_lag(walk, actions, episodes, [0, 1]) == 3
    assert best_copy_lag(walk, walk, episodes, [0, 1]) == 0


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


def reference_table(stdout: str) -> dict[str, tuple[float, float, float]]:
    """{joint: (IDM, ridge, copy)} from the dry run's table."""
    rows = re.findall(r"^\s+(\S+\.pos)\s+(-?[\d.]+)\s+(-?[\d.]+)\s+(-?[\d.]+) \(k=\d+\)", stdout, re.MULTILINE)
    return {name: (float(idm), float(ridge), float(copy)) for name, idm, ridge, copy in rows}


def test_the_default_idm_of_a_delayed_arm_is_not_below_the_ridge_regression_on_any_joint(delayed_arm, delayed_arm_run):
    _, held_out = delayed_arm
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={delayed_arm_run / CHECKPOINT}", "--dataset.repo_id=local/x",
        f"--dataset.root={held_out}", "--dry_run=true", check=True,
    )  # fmt: skip
    table = reference_table(result.stdout)
    assert len(table) == 6, result.stdout
    for joint, (idm, ridge, _) in table.items():
        assert idm >= ridge - 0.005, f"{joint}: IDM {idm} vs ridge {ridge}\n{result.stdout}"
    assert "below the ridge regression" not in result.stdout


def test_the_window_reaches_past_the_delay_and_is_recorded_and_reloaded(delayed_arm_run):
    checkpoint = delayed_arm_run / CHECKPOINT
    config = json.loads((checkpoint / "config.json").read_text())
    assert config["joint_state_columns"] == list(range(6))
    assert DELAY + 1 <= config["idm_lag"] <= DELAY + 3  # the servo's response adds a frame or two to the delay
    policy = IUPEPolicy.from_pretrained(checkpoint)
    assert policy.config.idm_lag == config["idm_lag"]
    assert max(policy.config.idm_window) == config["idm_lag"] + 1 + config["idm_context"]
    assert bool(policy.idm_encoder.fitted)
    window = torch.randn(3, len(policy.config.idm_window), 6) * 30
    # The reloaded model labels a window as the state at the lag plus corrections, not from scratch.
    with torch.no_grad():
        mean = policy.idm_head.mode(policy.eval().idm_window_output(window))
    copied = window[:, policy.config.idm_window.index(policy.config.idm_lag)]
    assert (mean - copied).abs().mean() < (mean - window[:, 0]).abs().mean()


def test_an_arm_idm_asked_of_an_unsupervised_run_or_of_cameras_is_refused_naming_the_flags():
    from lerobot_iupe.policy.configuration_iupe import IUPEConfig

    with pytest.raises(ValueError, match="joint_state_columns.*needs --policy.supervised=true"):
        IUPEConfig(joint_state_columns=[0, 1])
    with pytest.raises(ValueError, match="idm_observation_keys.*joint_state_columns=\\[\\]"):
        IUPEConfig(supervised=True, joint_state_columns=[0], idm_observation_keys=["observation.images.front"])
    assert IUPEConfig(supervised=True, joint_state_columns=[]).idm_window == [0, 1]
