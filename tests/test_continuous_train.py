"""IUPE with continuous actions through the real LeRobot CLIs: LunarLander learning, lerobot-eval on a continuous
checkpoint, the SO-101 plugin env (several observation keys, lerobot-train's own --env flags, no meta/iupe.json),
and rollouts in a lerobot_env_* plugin's own env type."""

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, collect, evaluate, run_in_process, train_args, train_once
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

from lerobot_iupe.benchmark import evaluate_checkpoint
from lerobot_iupe.data.readers import column_array, load_transitions
from lerobot_iupe.envs.configs import LunarLanderEnvConfig, action_space_of, env_settings
from lerobot_iupe.ilpo import ILPOPolicy
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy
from lerobot_iupe.policy.training import IUPETrainer


@pytest.fixture(scope="session")
def lunar_data(data_dir):
    args = ("--env.type=lunarlander", "--agent=expert", "--episodes=5")
    return {
        "expert": collect(data_dir, "lunar-expert", *args),
        "expert-actions": collect(data_dir, "lunar-expert-actions", *args, "--keep_actions=true"),
        "random": collect(
            data_dir, "lunar-random", "--env.type=lunarlander", "--agent=random", "--episodes=40", "--seed=1000"
        ),  # fmt: skip
    }


@pytest.fixture(scope="session")
def lunar_run(lunar_data, shared_dir):
    out = shared_dir / "runs" / "lunar"
    flags = ["--steps=300", "--batch_size=64", "--save_freq=300", "--policy.cycle_steps=100"]
    return train_once(out, *train_args(lunar_data["expert"], lunar_data["random"], out, *flags,
                                       "--policy.rollout_episodes=2"))  # fmt: skip


def main_engine_agreement(predicted: np.ndarray, true: np.ndarray) -> float:
    """Labels scored by their effect: LunarLander's main engine fires only for a[0] > 0 (a dead zone below)."""
    return float(((predicted[:, 0] > 0) == (true[:, 0] > 0)).mean())


def test_iupe_learns_lunarlander_action_effects_from_state_only_demos(lunar_run, lunar_data):
    policy = IUPEPolicy.from_pretrained(lunar_run / CHECKPOINT).eval()
    assert policy.config.is_continuous and policy.config.action_names == ["main_engine", "lateral_engines"]
    records = (lunar_run / CHECKPOINT / "iupe_cycles.jsonl").read_text().splitlines()
    r2 = [json.loads(line)["idm_r2"] for line in records]
    assert len(r2) == 3 and min(r2) > 0.5  # the IDM learns the action effects from random pre-demonstrations
    truth = load_transitions(
        LeRobotDataset("local/x", root=lunar_data["expert-actions"]), policy.config.observation_keys
    )
    states, next_states = torch.as_tensor(truth.states), torch.as_tensor(truth.next_states)
    with torch.no_grad():
        labels = policy.idm_head.mode(policy.idm_output(states, next_states)).numpy()
        acted = policy.pm_head.mode(policy.pm_output(states)).numpy()
    fires = (truth.actions[:, 0] > 0).mean()
    chance = max(fires, 1 - fires)
    # the expert's hidden actions, recovered by their effect (IDM) and imitated (policy), well above chance
    assert main_engine_agreement(labels, truth.actions) > chance + 0.1
    assert main_engine_agreement(acted, truth.actions) > chance + 0.1
    low, high = np.array(policy.config.action_low), np.array(policy.config.action_high)
    assert (acted >= low).all() and (acted <= high).all()


def test_lerobot_eval_runs_a_continuous_checkpoint_under_both_rules(lunar_run, tmp_path):
    """lerobot-eval applies --policy.eval_mode to a Gaussian head and scores what the benchmark's evaluation scores."""
    returns = {}
    for mode in ("argmax", "sample"):
        cli = evaluate(
            lunar_run / CHECKPOINT, tmp_path / mode, "--env.type=lunarlander", "--env.episode_length=100",
            f"--policy.eval_mode={mode}", episodes=2,
        )  # fmt: skip
        ours = evaluate_checkpoint(lunar_run / CHECKPOINT, LunarLanderEnvConfig(episode_length=100), 2, mode)
        assert cli["n_episodes"] == 2 and cli["avg_sum_reward"] == pytest.approx(ours["avg_sum_reward"])
        returns[mode] = cli["avg_sum_reward"]
    assert returns["argmax"] != pytest.approx(returns["sample"])  # draws are not the mode


def test_so101_plugin_env_trains_from_lerobot_train_env_flags_without_package_metadata(data_dir, tmp_path):
    env_args = ("--env.type=so101_pickplace", "--env.episode_length=30")
    expert = collect(data_dir, "so101-expert", *env_args, "--agent=expert", "--episodes=2")
    random = collect(data_dir, "so101-random", *env_args, "--agent=random", "--episodes=6", "--seed=1000")
    bare = tmp_path / "so101-expert-bare"  # as if written by another tool: no meta/iupe.json
    shutil.copytree(expert, bare)
    (bare / "meta" / "iupe.json").unlink()
    out = tmp_path / "run"
    flags = ["--steps=20", "--batch_size=16", "--save_freq=20", "--policy.cycle_steps=10",
             "--policy.rollout_episodes=2", *env_args, "--env_eval_freq=0"]  # fmt: skip
    run_in_process("lerobot-train", *train_args(bare, random, out, *flags), check=True)
    policy = IUPEPolicy.from_pretrained(out / CHECKPOINT)
    assert policy.config.observation_keys == [OBS_STATE, OBS_ENV_STATE]
    assert policy.config.env_settings["type"] == "so101_pickplace"
    assert policy.config.action_low == [-1.0, -1.0, -1.0, 0.0] and policy.config.action_high == [1.0] * 4
    records = (out / CHECKPOINT / "iupe_cycles.jsonl").read_text().splitlines()
    assert len(records) == 2


def test_rollouts_run_in_a_lerobot_env_plugins_own_env_type():
    from lerobot_env_so101.configuration_so101 import SO101Env

    env_cfg = SO101Env(episode_length=6)  # the plugin's type, made by LeRobot's make_env
    space = action_space_of(env_cfg)
    config = IUPEConfig(
        input_features={
            OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(14,)),
            OBS_ENV_STATE: PolicyFeature(type=FeatureType.ENV, shape=(3,)),
        },
        output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(4,))},
        action_low=space.low.tolist(),
        action_high=space.high.tolist(),
        env_settings=env_settings(env_cfg),
        device="cpu",
    )
    policy = IUPEPolicy(config)
    trainer = IUPETrainer(policy, dataset_meta=None, seed=0)
    trainer.use_env(env_cfg)
    episodes, successes, returns, _ = trainer.rollout(2, seed=0, explore=True)
    assert [len(e) for e in episodes] == [6, 6]
    assert episodes[0].states.shape == (6, 17) and episodes[0].actions.shape == (6, 4)
    assert (episodes[0].actions >= space.low).all() and (episodes[0].actions <= space.high).all()
    np.testing.assert_array_equal(episodes[0].states[1:], episodes[0].next_states[:-1])  # aligned steps
    assert successes.tolist() == [False, False]  # the plugin reports `succeed`, which LeRobot does not read


def test_a_full_iupe_checkpoint_relabels_state_only_lunarlander_data_with_named_float_actions(
    lunar_run, lunar_data, tmp_path
):
    dataset = tmp_path / "lunar-expert"
    shutil.copytree(lunar_data["expert"], dataset)
    run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={lunar_run / CHECKPOINT}", "--dataset.repo_id=local/lunar-expert",
        f"--dataset.root={dataset}", check=True
    )  # fmt: skip
    relabelled = LeRobotDataset("local/lunar-expert", root=dataset)
    feature = relabelled.meta.features[ACTION]
    assert feature["dtype"] == "float32" and tuple(feature["shape"]) == (2,)
    assert feature["names"] == ["main_engine", "lateral_engines"]
    labels = column_array(relabelled.hf_dataset, ACTION)
    assert labels.shape == (relabelled.meta.total_frames, 2) and labels.dtype == np.float32
    assert (labels >= -1).all() and (labels <= 1).all() and labels.std(axis=0).min() > 0.01
    np.testing.assert_allclose(relabelled.meta.stats[ACTION]["mean"], labels.mean(axis=0), rtol=1e-5, atol=1e-6)


def test_relabel_pulls_lunarlander_labels_toward_the_observation_and_records_it(lunar_run, lunar_data, tmp_path):
    """By default an IDM of cameras and state pulls continuous labels toward the observation by 1 std: they differ
    from the IDM's own (``--pull_to_observation=0``), stay in the action's bounds, each episode's last frame repeats
    the one before it, and meta/iupe.json records the pull."""

    def written(name: str, *extra: str) -> tuple[np.ndarray, LeRobotDataset]:
        root = tmp_path / name
        shutil.copytree(lunar_data["expert"], root)
        run_in_process(
            "lerobot-iupe-relabel", f"--policy.path={lunar_run / CHECKPOINT}", f"--dataset.repo_id=local/{name}",
            f"--dataset.root={root}", *extra, check=True
        )  # fmt: skip
        dataset = LeRobotDataset(f"local/{name}", root=root)
        return column_array(dataset.hf_dataset, ACTION), dataset

    own, _ = written("own", "--pull_to_observation=0")
    moved, dataset = written("pulled")
    assert not np.allclose(own, moved) and (moved >= -1).all() and (moved <= 1).all()
    last = np.asarray(dataset.meta.episodes["dataset_to_index"]) - 1
    np.testing.assert_array_equal(moved[last], moved[last - 1])
    recorded = json.loads((dataset.root / "meta" / "iupe.json").read_text())["relabelled_by"]
    assert recorded["pull_to_observation"] == 1.0


def test_ilpo_remaps_continuous_actions_by_regression(lunar_data, tmp_path):
    """ILPO on a Box action (not in the paper): |Z| = 2 per dimension, the ARN's Gaussian head regresses the
    executed action; its online score is then a squared error, and the policy acts inside the bounds."""
    out = tmp_path / "ilpo"
    expert = lunar_data["expert"]
    run_in_process(
        "lerobot-train", "--policy.type=ilpo", f"--dataset.repo_id=local/{expert.name}", f"--dataset.root={expert}",
        "--dataset.video_backend=pyav", f"--output_dir={out}", "--num_workers=0", "--policy.device=cpu",
        "--wandb.enable=false", "--steps=20", "--batch_size=32", "--policy.remap_steps=80", check=True
    )  # fmt: skip
    checkpoint = out / CHECKPOINT
    summary = json.loads((checkpoint / "ilpo_remapping.json").read_text())
    assert len(summary["z_star_usage"]) == 4 and summary["arn_online_mse"] >= 0
    policy = ILPOPolicy.from_pretrained(checkpoint).eval()
    batch = {key: torch.randn(3, *policy.config.input_features[key].shape) for key in policy.config.observation_keys}
    action = policy.select_action(batch)
    low, high = torch.tensor(policy.config.action_low), torch.tensor(policy.config.action_high)
    assert action.shape == (3, 2) and ((action >= low) & (action <= high)).all()
