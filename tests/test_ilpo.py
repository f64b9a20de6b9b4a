"""ILPO (--policy.type=ilpo): its losses against the note's formulas, a latent model that must separate actions it
never saw, the remapping that grounds them, and the real lerobot-train → lerobot-eval path on CartPole."""

import json
import shutil
from itertools import permutations

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, evaluate, run_in_process, train_once
from lerobot.configs import FeatureType, PolicyFeature

from lerobot_iupe.ilpo import ILPOConfig, ILPOPolicy
from lerobot_iupe.ilpo.latent_model import LatentActionEmbedding, best_latent, expected_state_loss, min_latent_loss
from lerobot_iupe.ilpo.remapping import arn_step

# Three actions, each moving a 2-D state its own way (plus noise): what ILPO must discover without labels.
EFFECTS = np.array([[0.3, 0.0], [0.0, 0.3], [-0.3, -0.3]], dtype=np.float32)


def test_the_min_loss_takes_each_samples_best_latent_and_trains_only_that_prediction():
    delta = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    predicted = torch.tensor([[[1.0, 1.0], [0.0, 0.0]], [[0.0, 2.0], [5.0, 5.0]]], requires_grad=True)
    loss, winner = min_latent_loss(delta, predicted)
    # sample 0: errors 1 (z=0) and 1 (z=1) → 1; sample 1: 0 (z=0) and 34 (z=1) → 0; mean 0.5, squared errors summed
    assert torch.isclose(loss, torch.tensor(0.5)) and winner[1] == 0
    loss.backward()
    assert predicted.grad[1, 1].abs().sum() == 0  # the losing latent of sample 1 gets no gradient
    assert predicted.grad[1, 0].abs().sum() == 0 and predicted.grad[0].abs().sum() > 0


def test_the_expected_state_loss_trains_pi_and_never_the_generator():
    delta = torch.tensor([[1.0, 0.0]])
    predicted = torch.tensor([[[2.0, 0.0], [0.0, 0.0]]], requires_grad=True)
    probabilities = torch.tensor([[0.25, 0.75]], requires_grad=True)
    loss = expected_state_loss(delta, predicted, probabilities)
    assert torch.isclose(loss, torch.tensor(0.25))  # (1 - 0.25·2)² = 0.25
    loss.backward()
    assert predicted.grad is None  # G never sees π's weighting (a G trained through L_exp fails here)
    assert probabilities.grad.abs().sum() > 0


def test_z_star_is_the_nearest_prediction_and_ties_go_to_the_lowest_latent():
    target = torch.tensor([[1.0, 1.0], [0.0, 0.0]])
    candidates = torch.tensor([[[0.0, 0.0], [1.0, 1.1], [3.0, 3.0]], [[1.0, 0.0], [0.0, 1.0], [5.0, 5.0]]])
    assert best_latent(target, candidates).tolist() == [1, 0]


def synthetic_policy(seed: int = 0, **config) -> ILPOPolicy:
    torch.manual_seed(seed)
    config = ILPOConfig(device="cpu", n_actions=3, **config)
    config.input_features = {"observation.state": PolicyFeature(FeatureType.STATE, (2,))}
    stats = {"observation.state": {"mean": np.zeros(2), "std": np.ones(2)}}
    return ILPOPolicy(config, dataset_stats=stats)


def transitions(n: int, seed: int, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``scale`` < 1: as in MountainCar, the actions push the second value (a velocity) by ``scale`` of their
    effect while the first (a position) moves by the velocity, whatever the action."""
    rng = np.random.default_rng(seed)
    states = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
    actions = rng.integers(3, size=n)
    effects = EFFECTS if scale == 1.0 else np.array([[0.0, -0.3], [0.0, 0.0], [0.0, 0.3]], dtype=np.float32)
    drift = np.zeros_like(states) if scale == 1.0 else np.stack([0.5 * states[:, 1], 0 * states[:, 0]], axis=1)
    noise = rng.normal(0, 0.01, (n, 2)).astype(np.float32)
    next_states = states + drift + scale * (effects[actions] + noise)
    return torch.as_tensor(states), torch.as_tensor(actions), torch.as_tensor(next_states)


def train_lpn(policy: ILPOPolicy, steps: int = 600, scale: float = 1.0) -> None:
    states, _, next_states = transitions(3000, seed=1, scale=scale)
    if policy.config.normalize:
        policy.fit_difference_scale(states, next_states)
    optimizer = torch.optim.Adam(policy.lpn.parameters(), lr=2e-4, betas=(0.5, 0.999))
    generator = torch.Generator().manual_seed(0)
    for _ in range(steps):
        rows = torch.randint(len(states), (32,), generator=generator)
        l_min, l_exp, _, _ = policy.lpn_losses(states[rows], next_states[rows])
        optimizer.zero_grad()
        (l_min + l_exp).backward()
        optimizer.step()


def purity(z: torch.Tensor, actions: torch.Tensor) -> float:
    """Share of transitions whose z* names their action under the best one-to-one map of latents to actions."""
    counts = np.zeros((3, 3))
    np.add.at(counts, (z.numpy(), actions.numpy()), 1)
    return max(sum(counts[z_, a] for z_, a in enumerate(p)) for p in permutations(range(3))) / len(z)


def test_the_latent_model_separates_unlabelled_actions_and_the_remapping_recovers_them():
    policy = synthetic_policy()
    train_lpn(policy)
    states, actions, next_states = transitions(1000, seed=2)  # held out from the LPN's training
    z = policy.explaining_latents(states, next_states)
    assert purity(z, actions) >= 0.95
    # the remapping, one step per transition as online, on its own (s, a, z*) buffer
    played, played_actions, played_next = transitions(1000, seed=3)
    played_z = policy.explaining_latents(played, played_next)
    optimizer = torch.optim.Adam(policy.arn.parameters(), lr=2e-3)
    rng = np.random.default_rng(0)
    for _ in range(1000):
        batch = torch.as_tensor(rng.integers(1000, size=32))
        arn_step(policy.arn, optimizer, played[batch], played_z[batch], played_actions[batch])
    predicted = policy.arn.head.mode(policy.arn(states, z))
    assert (predicted == actions).float().mean() >= 0.95


def test_a_latent_model_blind_to_z_fails_the_separation(monkeypatch):
    """The check above can fail: a generator that ignores z predicts one difference for every latent action."""
    monkeypatch.setattr(LatentActionEmbedding, "forward", lambda self, z: torch.zeros(len(z), self.linear.out_features))
    policy = synthetic_policy()
    train_lpn(policy)
    states, actions, next_states = transitions(1000, seed=2)
    assert purity(policy.explaining_latents(states, next_states), actions) < 0.5


def test_normalised_differences_separate_actions_whose_effect_the_raw_error_drowns():
    """--policy.normalize: with the actions' effects 50× smaller than a drift they share, the raw summed error
    lets the generator fit the drift and never split the latents; scaled per value, they separate."""
    purities = {}
    for normalize in (False, True):
        policy = synthetic_policy(normalize=normalize)
        train_lpn(policy, scale=0.02)
        states, actions, next_states = transitions(1000, seed=2, scale=0.02)
        purities[normalize] = purity(policy.explaining_latents(states, next_states), actions)
    assert purities[True] >= 0.9 > purities[False]


@pytest.mark.parametrize("latent_actions", [1, -1])
def test_a_single_latent_action_is_refused_naming_the_flag(latent_actions):
    with pytest.raises(ValueError, match="--policy.latent_actions"):
        ILPOConfig(latent_actions=latent_actions)


def ilpo_args(expert, out, *extra: str) -> list[str]:
    return [
        "--policy.type=ilpo", f"--dataset.repo_id=local/{expert.name}", f"--dataset.root={expert}",
        "--dataset.video_backend=pyav", f"--output_dir={out}", "--num_workers=0", "--policy.device=cpu",
        "--wandb.enable=false", "--batch_size=32", "--seed=3", *extra,
    ]  # fmt: skip


@pytest.fixture(scope="session")
def ilpo_run(cartpole_expert, shared_dir):
    out = shared_dir / "runs" / "ilpo"
    extra = ["--steps=400", "--save_freq=400", "--policy.remap_steps=300", "--policy.selection_episodes=2"]
    return train_once(out, *ilpo_args(cartpole_expert, out, *extra))


def test_lerobot_train_then_lerobot_eval_run_ilpo_on_cartpole(ilpo_run, tmp_path):
    checkpoint = ilpo_run / CHECKPOINT
    summary = json.loads((checkpoint / "ilpo_remapping.json").read_text())
    assert summary["remap_env_steps"] == 300 and summary["lpn_steps"] == 400
    assert len(summary["z_star_usage"]) == 2 and abs(sum(summary["expert_winner_usage"]) - 1) < 1e-6
    assert 0.0 <= summary["arn_online_accuracy"] <= 1.0
    assert [r["step"] for r in summary["selection"]] == [100, 200, 300] and summary["selection_env_steps"] > 0
    overall = evaluate(checkpoint, tmp_path / "eval", "--env.type=cartpole", episodes=2)
    assert overall["n_episodes"] == 2


def test_a_resumed_ilpo_run_ends_where_an_uninterrupted_one_does(cartpole_expert, tmp_path):
    extra = ["--save_freq=20", "--policy.remap_steps=60"]
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    run_in_process("lerobot-train", *ilpo_args(cartpole_expert, whole, "--steps=40", *extra), check=True)
    run_in_process("lerobot-train", *ilpo_args(cartpole_expert, parts, "--steps=20", *extra), check=True)
    run_in_process(
        "lerobot-train",
        f"--config_path={parts / CHECKPOINT / 'train_config.json'}",
        "--resume=true",
        "--steps=40",
        check=True,
    )
    model = "model.safetensors"
    assert (parts / CHECKPOINT / model).read_bytes() == (whole / CHECKPOINT / model).read_bytes()
    summaries = [json.loads((p / CHECKPOINT / "ilpo_remapping.json").read_text()) for p in (whole, parts)]
    assert summaries[0] == summaries[1]


def test_ilpo_without_an_env_stops_before_training_naming_the_flag(cartpole_expert, tmp_path):
    bare = tmp_path / "bare"  # the expert data without meta/iupe.json: no env recorded
    shutil.copytree(cartpole_expert, bare)
    (bare / "meta" / "iupe.json").unlink()
    result = run_in_process("lerobot-train", *ilpo_args(bare, tmp_path / "out", "--steps=2"), check=False)
    assert result.returncode != 0 and "--env.type" in result.stderr + result.stdout
    assert not (tmp_path / "out" / "checkpoints").exists()  # refused before any checkpoint is written
