"""The linear part under the cycle's continuous IDM (policy/linear_prior.py): velocities that are the state's
differences are labelled at once, a saved checkpoint labels the same, and one saved before the linear part existed
labels as it did."""

import numpy as np
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.utils.constants import OBS_STATE

from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.idm_fit import fit_idm
from lerobot_iupe.policy.linear_prior import LinearPrior, contiguous_folds
from lerobot_iupe.policy.modeling_iupe import IUPEPolicy
from lerobot_iupe.relabel.labelling import labelling_pass
from lerobot_iupe.relabel.references import linear_part_references


def velocity_transitions(count: int, seed: int) -> Transitions:
    """A random walk of three values whose first two steps are the actions, times 3 (the third is a distractor)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(0, 0.1, (count, 3)).astype(np.float32)
    states = np.cumsum(np.concatenate([np.zeros((1, 3), np.float32), steps]), axis=0)
    return Transitions.pairs(states[:-1], np.clip(3.0 * steps[:, :2], -1, 1), states[1:])


def continuous_policy(linear: bool | None = True) -> IUPEPolicy:
    config = IUPEConfig(
        input_features={OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(3,))},
        action_low=[-1.0, -1.0], action_high=[1.0, 1.0], action_names=["vx", "vy"], device="cpu", idm_epochs=1,
        idm_linear_part=linear,
    )  # fmt: skip
    torch.manual_seed(0)
    return IUPEPolicy(config)


def test_the_cycles_idm_labels_velocities_from_the_state_differences_in_one_epoch(tmp_path):
    assert continuous_policy(linear=None).idm_prior is None  # the cycle's default, and checkpoints from before it
    policy = continuous_policy()
    assert isinstance(policy.idm_prior, LinearPrior)
    data, held_out = velocity_transitions(2000, 0), velocity_transitions(500, 1)
    optimizer = torch.optim.Adam(policy.idm_parameters(), lr=1e-3)
    _, score = fit_idm(policy, optimizer, data, held_out, np.random.default_rng(0))
    assert score > 0.98  # the network alone, one epoch of 32 batches: far below
    window = torch.as_tensor(held_out.windows[:50])
    policy.eval()
    with torch.no_grad():
        labels = policy.idm_head.mode(policy.idm_window_output(window))
    policy.save_pretrained(tmp_path / "checkpoint")
    loaded = IUPEPolicy.from_pretrained(tmp_path / "checkpoint").eval()
    with torch.no_grad():
        torch.testing.assert_close(loaded.idm_head.mode(loaded.idm_window_output(window)), labels)

    # A checkpoint without the linear part (saved before it existed) loads unfitted and labels by its network alone.
    weights = {k: v for k, v in policy.state_dict().items() if not k.startswith("idm_prior.")}
    older = continuous_policy()
    older.load_state_dict(weights, strict=False)
    older.eval()
    assert not bool(older.idm_prior.fitted)
    with torch.no_grad():
        network = older.idm_head.mode(older.idm_window_output(window))
    assert not torch.allclose(network, labels)


def test_copies_count_once_and_folds_are_contiguous():
    assert contiguous_folds(6).tolist() == [0, 1, 2, 3, 4, 5]
    assert contiguous_folds(40).tolist() == np.repeat(np.arange(20), 2).tolist()
    prior = LinearPrior(2, [0, 1, 2], 2)
    data = velocity_transitions(300, 2)
    copies = data.take(np.r_[np.arange(300), np.zeros(3000, dtype=np.int64)])  # one transition drawn 3000 times
    prior.fit(prior.features(copies.windows), copies.actions, np.array([True, False]))
    alone = LinearPrior(2, [0, 1, 2], 2)
    alone.fit(alone.features(data.windows), data.actions, np.array([True, False]))
    torch.testing.assert_close(prior.weight, alone.weight)
    assert not prior.weight[:, 1].any() and prior.bias[1] == 0  # a dimension left out stays at 0


def test_the_dry_run_scores_the_linear_part_alone_beside_the_idm():
    policy = continuous_policy()
    data, held_out = velocity_transitions(2000, 0), velocity_transitions(500, 1)
    fit_idm(policy, torch.optim.Adam(policy.idm_parameters(), lr=1e-3), data, held_out, np.random.default_rng(0))
    policy.eval()
    window = torch.as_tensor(held_out.windows)
    with torch.no_grad():
        output = labelling_pass(policy, window)
    assert output.shape == (len(window), 2 * 2 + 2)  # mean and log-std per dimension, then the linear part's labels
    torch.testing.assert_close(output[:, 4:], policy.idm_prior(window))
    references = linear_part_references(policy, output[:, 4:].numpy(), held_out.actions, np.arange(len(window)))
    assert references["ridge"][0] > 0.98 and references["lag"] == [None, None]


def test_the_first_idm_labels_by_its_linear_part_and_later_ones_judge_the_network_on_the_policys_own_rollouts():
    """Fitted on play alone, the network's correction moved Meta-World's expert labels below the linear part's
    (benchmarks/cycle_linear_part.md): with no rollout of the policy's own to judge it on, its share is 0."""

    # A second dimension the linear part cannot read (the square of a step), which the network learns.
    def squared(transitions: Transitions) -> Transitions:
        step = transitions.next_states[:, 0] - transitions.states[:, 0]
        transitions.actions[:, 1] = np.clip(100.0 * step**2 - 1.0, -1, 1)
        return transitions

    policy = continuous_policy()
    play, held_play = squared(velocity_transitions(4000, 0)), squared(velocity_transitions(500, 1))
    optimizer = torch.optim.Adam(policy.idm_parameters(), lr=1e-3)
    for seed in range(3):  # a network that helps on held-out play (an earlier rule kept half of it or more)
        fit_idm(policy, optimizer, play, held_play, np.random.default_rng(seed))
    assert policy.idm_prior.gate.tolist() == [0.0, 0.0]
    window = torch.as_tensor(held_play.windows[:50])
    policy.eval()
    with torch.no_grad():
        labels = policy.idm_head.mode(policy.idm_window_output(window))
        torch.testing.assert_close(labels, policy.idm_prior(window).clamp(-1, 1))
    # Judged on the policy's own held-out rollout transitions, the network's share is kept.
    own, own_held = squared(velocity_transitions(4000, 2)), squared(velocity_transitions(500, 3))
    policy.train()
    for seed in range(3):
        fit_idm(policy, optimizer, own, held_play, np.random.default_rng(seed), own_held)
    assert policy.idm_prior.gate[1] > 0.5, policy.idm_prior.gate
