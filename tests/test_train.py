"""IUPE through the real lerobot-train and lerobot-eval CLIs."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, collect, evaluate, run_in_process, train_args
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from safetensors.torch import load_file
from test_loop import build, frame_batch

from lerobot_iupe.benchmark import evaluate_checkpoint
from lerobot_iupe.data.readers import column_array
from lerobot_iupe.envs.configs import CartPoleEnvConfig, MazeEnvConfig
from lerobot_iupe.policy import IUPEPolicy
from lerobot_iupe.policy.training import CYCLES_FILE


def test_iupe_learns_cartpole_from_state_only_demos(cartpole_run, tmp_path):
    checkpoint = cartpole_run / CHECKPOINT
    assert (checkpoint / "model.safetensors").exists() and (checkpoint / "config.json").exists()
    # 20 evaluation episodes on seeds 500000… never used in training (data 0…9 and 1000…1399, rollouts ≥ 1e6), by
    # lerobot-eval's path without its videos (the CLI itself runs on the maze checkpoint below)
    result = evaluate_checkpoint(checkpoint, CartPoleEnvConfig(), episodes=20)
    assert result["avg_sum_reward"] >= 475
    assert result["pc_success"] >= 95


@pytest.mark.parametrize("mode", ["argmax", "sample"])
def test_lerobot_eval_of_an_image_checkpoint_matches_the_benchmark_evaluation(maze_run, tmp_path, mode):
    """lerobot-eval and the benchmark's evaluation are one evaluation path, under either --policy.eval_mode."""
    cli = evaluate(
        maze_run / CHECKPOINT, tmp_path / "eval", "--env.type=maze", "--env.size=3", f"--policy.eval_mode={mode}",
        episodes=4,
    )  # fmt: skip
    ours = evaluate_checkpoint(maze_run / CHECKPOINT, MazeEnvConfig(size=3), episodes=4, eval_mode=mode)
    assert cli["n_episodes"] == 4
    assert (cli["avg_sum_reward"], cli["pc_success"]) == pytest.approx((ours["avg_sum_reward"], ours["pc_success"]))


def make_dataset_without_observation(root):
    dataset = LeRobotDataset.create(
        "local/no-obs",
        fps=10,
        root=root,
        features={"next.reward": {"dtype": "float32", "shape": (1,), "names": None}},
        use_videos=False,
    )
    for _ in range(3):
        dataset.add_frame({"next.reward": np.array([1.0], dtype=np.float32), "task": "t"})
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
        ("no_observation", "the expert dataset has no observation IUPE can read"),
        ("pre_without_action", "have no 'action' column"),
        ("pre_other_state_size", "'observation.state' has shape (2,) in the pre-demonstrations local/mc but (4,)"),
        ("pre_other_action_count", "disagree on the env type: 'mountaincar' vs 'cartpole'"),
        ("env_mismatch", "but (6,) in env acrobot"),
        ("missing_pre", "is not a LeRobot dataset"),
        ("rollout_layouts_without_layouts", "--policy.rollout_layouts=2 must be below the number of distinct layouts"),
    ],
)
def test_bad_training_input_fails_before_training(case, message, cartpole_expert, cartpole_random, tmp_path):
    expert, pre, policy = cartpole_expert, cartpole_random, {}
    if case == "no_observation":
        expert = make_dataset_without_observation(tmp_path / "no-obs")
        policy = {"n_actions": 2, "env_settings": {"type": "cartpole"}}
    elif case == "pre_without_action":
        pre = cartpole_expert
    elif case == "pre_other_state_size":
        pre = collect(tmp_path, "mc", "--env.type=mountaincar", "--agent=random", "--episodes=1")
    elif case == "pre_other_action_count":
        pre = tmp_path / "cartpole-random-copy"
        shutil.copytree(cartpole_random, pre)
        relabel_env(pre, {"type": "mountaincar", "episode_length": 200})
    elif case == "env_mismatch":
        policy = {"env_settings": {"type": "acrobot"}}
    elif case == "missing_pre":
        pre = tmp_path / "does-not-exist"
    elif case == "rollout_layouts_without_layouts":  # CartPole has no layouts to keep apart
        policy = {"rollout_layouts": 2}
    if case == "env_mismatch":  # through lerobot-train itself; the other cases where lerobot-train raises them
        out = tmp_path / "train"
        flags = [f"--policy.{k}={json.dumps(v)}" for k, v in policy.items()]
        result = run_in_process("lerobot-train", *train_args(expert, pre, out, "--steps=2", *flags))
        assert result.returncode != 0 and message in result.stderr + result.stdout
        assert not (out / "checkpoints").exists()
        return
    with pytest.raises((ValueError, FileNotFoundError)) as error:  # building the policy, or its first step
        build(expert, pre, **policy).forward(frame_batch(expert, 4))
    assert message in str(error.value)


def cycles_of(run: Path) -> list[dict]:
    return [json.loads(line) for line in (run / CHECKPOINT / CYCLES_FILE).read_text().splitlines()]


def test_bco_is_iupe_with_its_switches_off(cartpole_run, cartpole_expert, cartpole_random, tmp_path):
    pre_transitions = LeRobotDatasetMetadata("local/r", root=cartpole_random).total_frames - 400  # 400 episodes
    pre_trained_on = pre_transitions - pre_transitions // 10  # a tenth of I_pre scores the IDM
    iupe = cycles_of(cartpole_run)
    assert all(c["sampled_set_size"] == pre_trained_on for c in iupe)  # |I^s| = |I_pre| less the held-out part
    assert all(c["idm_held_out"] >= pre_transitions // 10 for c in iupe)
    assert any(c["label_non_map"] > 0 for c in iupe)
    assert all(c["selection_episodes"] == 8 for c in iupe) and iupe[-1]["selection_s"] > 0  # its own, by the mode
    bco = tmp_path / "bco"
    switches = ["--policy.sampling=false", "--policy.exploration=false", "--policy.attention=false"]
    short = ["--steps=20", "--batch_size=64", "--policy.cycle_steps=10", "--policy.rollout_episodes=4"]
    run_in_process("lerobot-train", *train_args(cartpole_expert, cartpole_random, bco, *short, *switches), check=True)
    cycles = cycles_of(bco)
    # BCO(α): I_pre plus every transition of the latest rollouts; argmax labels; no attention modules
    assert all(c["sampled_set_size"] > pre_trained_on + 4 for c in cycles)
    assert all(c["label_non_map"] == 0 for c in cycles)
    # its rollouts play the mode, as lerobot-eval does: they select the model, no episode is played for it alone
    assert cycles[-1]["selection_s"] == 0
    assert all(c["selection_env_success_rate"] == c["env_success_rate"] for c in cycles)
    assert not [k for k in load_file(bco / CHECKPOINT / "model.safetensors") if "gamma" in k]


def test_supervised_training_teaches_the_policy_and_the_idm_the_true_actions(
    cartpole_labelled, cartpole_random, tmp_path
):
    labelled = cartpole_labelled
    bc = tmp_path / "bc"
    run_in_process(
        "lerobot-train",
        *train_args(
            labelled,
            cartpole_random,
            bc,
            "--steps=150",
            "--batch_size=64",
            "--policy.supervised=true",
            "--policy.idm_context=0",
        ),  # fmt: skip
        check=True,
    )
    assert not (bc / CHECKPOINT / CYCLES_FILE).exists()  # no rollouts, no cycles
    policy = IUPEPolicy.from_pretrained(bc / CHECKPOINT)
    dataset = LeRobotDataset("local/labelled", root=labelled)
    states = torch.as_tensor(column_array(dataset.hf_dataset, "observation.state"))
    actions = column_array(dataset.hf_dataset, "action").reshape(-1)
    agreement = (policy.pm_output(states).argmax(-1).numpy() == actions).mean()
    assert agreement >= 0.9
    episodes = column_array(dataset.hf_dataset, "episode_index")
    inner = np.flatnonzero(episodes[:-1] == episodes[1:])
    idm_agreement = (policy.idm_output(states[inner], states[inner + 1]).argmax(-1).numpy() == actions[inner]).mean()
    assert idm_agreement >= 0.9  # the IDM learned from the same true actions


def test_supervised_without_actions_is_refused(cartpole_expert, cartpole_random, tmp_path):
    out = tmp_path / "bc"
    result = run_in_process(
        "lerobot-train",
        *train_args(cartpole_expert, cartpole_random, out, "--steps=2", "--policy.supervised=true"),
        check=False,
    )
    assert result.returncode != 0 and "--keep_actions=true" in result.stderr + result.stdout
    assert not (out / "checkpoints").exists()


def without_timing(cycles: list[dict]) -> list[dict]:
    return [{k: v for k, v in c.items() if not k.endswith("_s")} for c in cycles]


@pytest.mark.parametrize("decay", ["0", "0.8"])  # with a weight average, it goes on from the saved one
def test_a_resumed_run_continues_exactly_where_an_uninterrupted_one_would_be(
    cartpole_expert, cartpole_random, tmp_path, decay
):
    args = ["--batch_size=64", "--save_freq=10", "--policy.cycle_steps=4", "--policy.rollout_episodes=4", "--seed=5"]
    args.append(f"--policy.ema_decay={decay}")
    whole = tmp_path / "whole"
    run_in_process(
        "lerobot-train", *train_args(cartpole_expert, cartpole_random, whole, "--steps=20", *args), check=True
    )
    parts = tmp_path / "parts"
    run_in_process(
        "lerobot-train", *train_args(cartpole_expert, cartpole_random, parts, "--steps=10", *args), check=True
    )
    config = parts / CHECKPOINT / "train_config.json"
    run_in_process("lerobot-train", f"--config_path={config}", "--resume=true", "--steps=20", check=True)
    # same cycle boundaries, rollout seeds, successes and selections (a worse cycle keeps the earlier selection)
    assert without_timing(cycles_of(parts)) == without_timing(cycles_of(whole))
    assert [c["step"] for c in cycles_of(whole)] == [4, 8, 12, 16, 20]
    model = "model.safetensors"
    assert (parts / CHECKPOINT / model).read_bytes() == (whole / CHECKPOINT / model).read_bytes()


def test_policy_path_fine_tunes_a_new_run_with_the_env_flags_given_now(
    cartpole_run, cartpole_expert, cartpole_random, tmp_path
):
    out = tmp_path / "fine-tune"
    args = train_args(cartpole_expert, cartpole_random, out, "--steps=20", "--policy.cycle_steps=10")
    args = [a for a in args if a != "--policy.type=iupe"]
    result = run_in_process(
        "lerobot-train", f"--policy.path={cartpole_run / CHECKPOINT}", "--env.type=cartpole",
        "--env.episode_length=100", "--policy.rollout_episodes=4", "--batch_size=64", *args, check=True,
    )  # fmt: skip
    assert "continuing from" not in result.stdout + result.stderr
    cycles = cycles_of(out)
    # a new run: its own cycles and steps, the first cycle selected (no best success carried over)
    assert [(c["cycle"], c["step"]) for c in cycles] == [(1, 10), (2, 20)] and cycles[0]["selected"]
    assert all(c["return"] <= 100 for c in cycles)  # rolled out under the 100-step cap given now
    config = json.loads((out / CHECKPOINT / "config.json").read_text())
    assert config["env_settings"] == {"type": "cartpole", "episode_length": 100}


def test_lerobot_seed_drives_iupe_unless_the_policy_seed_is_given(cartpole_expert, cartpole_random, tmp_path):
    def train(name: str, *extra: str) -> Path:
        out = tmp_path / name
        short = ["--steps=8", "--batch_size=64", "--policy.cycle_steps=4", "--policy.rollout_episodes=2"]
        run_in_process("lerobot-train", *train_args(cartpole_expert, cartpole_random, out, *short, *extra), check=True)
        return out

    def rollout_seeds(run: Path) -> list[int]:
        return [c["rollout_seed"] for c in cycles_of(run)]

    a, b, other = train("a", "--seed=3"), train("b", "--seed=3"), train("other", "--seed=4")
    assert (a / CHECKPOINT / "model.safetensors").read_bytes() == (b / CHECKPOINT / "model.safetensors").read_bytes()
    assert rollout_seeds(a) == rollout_seeds(b) and rollout_seeds(other) != rollout_seeds(a)
    fixed3, fixed4 = train("fixed3", "--seed=3", "--policy.seed=7"), train("fixed4", "--seed=4", "--policy.seed=7")
    assert rollout_seeds(fixed3) == rollout_seeds(fixed4) != rollout_seeds(a)
