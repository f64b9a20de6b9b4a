"""IUPE through the real lerobot-train and lerobot-eval CLIs."""

import json
import shutil

import numpy as np
import pytest
from conftest import CHECKPOINT, evaluate, run_cli, train_args
from lerobot.datasets import LeRobotDataset


def test_iupe_learns_cartpole_from_state_only_demos(cartpole_run, tmp_path):
    checkpoint = cartpole_run / CHECKPOINT
    assert (checkpoint / "model.safetensors").exists() and (checkpoint / "config.json").exists()
    # 20 evaluation episodes on seeds 500000… never used in training (data 0…9 and 1000…1399, rollouts ≥ 1e6)
    result = evaluate(checkpoint, tmp_path / "eval", "--env.type=cartpole", episodes=20)
    assert result["avg_sum_reward"] >= 475
    assert result["pc_success"] >= 95


def test_maze_policy_trains_and_lerobot_eval_runs(maze_run, tmp_path):
    result = evaluate(maze_run / CHECKPOINT, tmp_path / "eval", "--env.type=maze", "--env.size=3", episodes=2)
    assert result["n_episodes"] == 2 and 0 <= result["pc_success"] <= 100


def make_dataset_without_observation(root):
    dataset = LeRobotDataset.create(
        "local/no-obs",
        fps=10,
        root=root,
        features={"observation.environment_state": {"dtype": "float32", "shape": (2,), "names": None}},
        use_videos=False,
    )
    for _ in range(3):
        dataset.add_frame({"observation.environment_state": np.array([0.0, 1.0], dtype=np.float32), "task": "t"})
    dataset.save_episode()
    dataset.finalize()
    return root


def relabel_env(root, env: dict):
    meta_path = root / "meta" / "iupe.json"
    meta = json.loads(meta_path.read_text())
    meta["env"] = env
    meta_path.write_text(json.dumps(meta))
    return root


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("no_observation", "neither 'observation.state' nor 'observation.image'"),
        ("pre_without_action", "have no 'action' column"),
        ("pre_other_state_size", "the pre-demonstrations' 'observation.state' has shape (2,)"),
        ("pre_other_action_count", "with 3 actions but the expert data's env has 2"),
        ("env_mismatch", "env acrobot observations have shape (6,)"),
        ("missing_pre", "is not a LeRobot dataset"),
    ],
)
def test_bad_training_input_fails_before_training(case, message, cartpole_expert, cartpole_random, data_dir, tmp_path):
    expert, pre, extra = cartpole_expert, cartpole_random, []
    if case == "no_observation":
        expert = make_dataset_without_observation(tmp_path / "no-obs")
        extra = ["--policy.n_actions=2", '--policy.env_settings={"type": "cartpole"}']
    elif case == "pre_without_action":
        pre = cartpole_expert
    elif case == "pre_other_state_size":
        pre = tmp_path / "mc"
        run_cli(
            "lerobot-iupe-collect",
            "--env.type=mountaincar",
            "--agent=random",
            "--episodes=1",
            "--dataset.repo_id=local/mc",
            f"--dataset.root={pre}",
        )
    elif case == "pre_other_action_count":
        pre = tmp_path / "cartpole-random-copy"
        shutil.copytree(cartpole_random, pre)
        relabel_env(pre, {"type": "mountaincar", "episode_length": 200})
    elif case == "env_mismatch":
        extra = ['--policy.env_settings={"type": "acrobot"}']
    elif case == "missing_pre":
        pre = tmp_path / "does-not-exist"
    out = tmp_path / "train"
    result = run_cli("lerobot-train", *train_args(expert, pre, out, "--steps=2", *extra), check=False)
    assert result.returncode != 0
    assert message in result.stderr + result.stdout
    assert not (out / "checkpoints").exists()


def test_bco_and_supervised_bc_run_through_the_same_loop(cartpole_expert, cartpole_random, data_dir, tmp_path):
    bco = tmp_path / "bco"
    run_cli(
        "lerobot-train",
        *train_args(
            cartpole_expert,
            cartpole_random,
            bco,
            "--steps=20",
            "--batch_size=64",
            "--policy.cycle_steps=10",
            "--policy.rollout_episodes=4",
            "--policy.sampling=false",
            "--policy.exploration=false",
            "--policy.attention=false",
        ),
    )
    config = json.loads((bco / CHECKPOINT / "config.json").read_text())
    assert (config["sampling"], config["exploration"], config["attention"]) == (False, False, False)
    labelled = data_dir / "cartpole-expert-labelled"
    run_cli(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=expert",
        "--episodes=3",
        "--keep_actions=true",
        "--dataset.repo_id=local/labelled",
        f"--dataset.root={labelled}",
    )
    bc = tmp_path / "bc"
    run_cli("lerobot-train", *train_args(labelled, cartpole_random, bc, "--steps=20", "--policy.supervised=true"))
    assert (bc / CHECKPOINT / "model.safetensors").exists()


def test_supervised_without_actions_is_refused(cartpole_expert, cartpole_random, tmp_path):
    out = tmp_path / "bc"
    result = run_cli(
        "lerobot-train",
        *train_args(cartpole_expert, cartpole_random, out, "--steps=2", "--policy.supervised=true"),
        check=False,
    )
    assert result.returncode != 0 and "--keep_actions=true" in result.stderr + result.stdout
    assert not (out / "checkpoints").exists()


def test_resume_continues_training(cartpole_expert, cartpole_random, tmp_path):
    out = tmp_path / "train"
    args = ["--steps=10", "--batch_size=64", "--save_freq=10", "--policy.cycle_steps=5", "--policy.rollout_episodes=2"]
    run_cli("lerobot-train", *train_args(cartpole_expert, cartpole_random, out, *args))
    config = out / CHECKPOINT / "train_config.json"
    result = run_cli("lerobot-train", f"--config_path={config}", "--resume=true", "--steps=20")
    assert "IUPE cycle" in result.stdout + result.stderr
    assert (out / "checkpoints" / "000020" / "pretrained_model" / "model.safetensors").exists()
