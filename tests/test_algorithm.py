import numpy as np
import pytest
import torch

from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.algorithm import (
    Transitions,
    apportion,
    build_sampled_set,
    choose_actions,
    frame_differences,
    held_out_split,
    performance,
    sampling_counts,
    selects,
    success_action_distribution,
)

N_ACTIONS = 3


def make_transitions(actions, tag: float) -> Transitions:
    actions = np.asarray(actions, dtype=np.int64)
    states = np.stack([np.full(len(actions), tag), np.arange(len(actions)) * 1.0], axis=1)
    return Transitions.pairs(states, actions, states + 1.0)


@pytest.fixture
def pre() -> Transitions:
    return make_transitions(np.repeat(np.arange(N_ACTIONS), 100), tag=0.0)


@pytest.fixture
def successful() -> Transitions:
    return make_transitions([0] * 30 + [1] * 10, tag=1.0)


def test_eq1_uses_successful_runs_only_and_sums_to_r():
    episodes = [np.array([0, 0, 1, 1]), np.array([2, 2, 2, 2]), np.array([0, 0, 0, 1])]
    p = success_action_distribution(episodes, np.array([True, False, True]), N_ACTIONS)
    np.testing.assert_allclose(p, [(0.5 + 0.75) / 3, (0.5 + 0.25) / 3, 0.0])
    assert p.sum() == pytest.approx(2 / 3)


def test_r_zero_gives_exactly_the_pre_demonstrations_even_when_unbalanced(successful):
    unbalanced = make_transitions([0] * 200 + [1] * 60 + [2] * 40, tag=0.0)
    sampled = build_sampled_set(unbalanced, successful, np.zeros(N_ACTIONS), 300, np.random.default_rng(0))
    assert np.all(sampled.states[:, 0] == 0.0)
    # I^s = I_pre: every pre-demonstration transition once (not a rebalanced draw)
    assert sorted(map(tuple, sampled.states)) == sorted(map(tuple, unbalanced.states))


def test_pre_share_is_inverse_probability_times_pre_frequency():
    # r = 0.5 all on action 0: pre weights 200·0.5, 60·1, 40·1 → 100 : 60 : 40 of the other 500
    from_success, from_pre = sampling_counts(np.array([0.5, 0.0, 0.0]), np.array([200, 60, 40]), 1000)
    assert from_success.tolist() == [500, 0, 0]
    assert from_pre.tolist() == [250, 150, 100]


def test_r_one_gives_only_successful_transitions(pre, successful):
    p = np.array([0.75, 0.25, 0.0])
    sampled = build_sampled_set(pre, successful, p, 200, np.random.default_rng(0))
    assert len(sampled) == 200 and np.all(sampled.states[:, 0] == 1.0)
    assert np.bincount(sampled.actions, minlength=3).tolist() == [150, 50, 0]


def test_max_success_share_keeps_pre_demonstrations_when_every_rollout_succeeds(pre, successful):
    # r = 1 capped at 0.8: P(a|E) scaled to [0.6, 0.2, 0]; pre weights 100·(1 − P) = 40 : 80 : 100 of the other 200
    from_success, from_pre = sampling_counts(np.array([0.75, 0.25, 0.0]), np.array([100, 100, 100]), 1000, 0.8)
    assert from_success.tolist() == [600, 200, 0]
    assert from_pre.tolist() == [36, 73, 91]
    sampled = build_sampled_set(pre, successful, np.array([0.75, 0.25, 0.0]), 200, np.random.default_rng(0),
                                max_success_share=0.8)  # fmt: skip
    assert (sampled.states[:, 0] == 0.0).sum() == 40  # a fifth from I_pre
    below = sampling_counts(np.array([0.5, 0.0, 0.0]), np.array([200, 60, 40]), 1000, 0.8)
    assert [c.tolist() for c in below] == [[500, 0, 0], [250, 150, 100]]  # r under the cap: the paper's rule


@pytest.mark.parametrize("size", [100, 301, 1000])
def test_mixed_shares_follow_eq1_and_inverse_probability(pre, successful, size):
    p = np.array([0.3, 0.1, 0.0])  # r = 0.4
    sampled = build_sampled_set(pre, successful, p, size, np.random.default_rng(1))
    assert len(sampled) == size
    from_success = sampled.states[:, 0] == 1.0
    assert abs(from_success.sum() - 0.4 * size) <= 1
    success_counts = np.bincount(sampled.actions[from_success], minlength=3)
    np.testing.assert_allclose(success_counts, p / p.sum() * round(0.4 * size), atol=1)
    pre_counts = np.bincount(sampled.actions[~from_success], minlength=3)
    inverse = (1 - p) / (1 - p).sum() * (size - round(0.4 * size))
    np.testing.assert_allclose(pre_counts, inverse, atol=1)
    assert (pre_counts > 0).all()  # every I_pre action still present


def test_every_pre_action_survives_while_r_below_one():
    from_success, from_pre = sampling_counts(np.array([0.9, 0.0, 0.0]), np.array([100, 100, 100]), 100)
    assert from_success.tolist() == [90, 0, 0]
    assert (from_pre >= 1).all() and from_pre.sum() == 10
    _, from_pre = sampling_counts(np.array([0.5, 0.49, 0.0]), np.array([100, 100, 100]), 1000)
    assert (from_pre >= 1).all() and from_pre.sum() == 10


def test_actions_absent_from_pre_demonstrations_get_no_share():
    _, from_pre = sampling_counts(np.zeros(3), np.array([5, 0, 5]), 10)
    assert from_pre.tolist() == [5, 0, 5]


def test_classes_smaller_than_their_share_are_drawn_with_replacement(pre):
    few = make_transitions([0, 1], tag=1.0)
    sampled = build_sampled_set(pre, few, np.array([0.5, 0.5, 0.0]), 50, np.random.default_rng(0))
    assert len(sampled) == 50 and np.all(sampled.states[:, 0] == 1.0)


def test_alignment_of_rollout_transitions_is_kept(pre):
    # synthetic rollout on a line: s_{t+1} = s_t + (a_t == 1) - (a_t == 0)
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 2, 50)
    positions = np.concatenate([[0], np.cumsum(np.where(actions == 1, 1, -1))]).astype(float)
    rollout = Transitions.pairs(positions[:-1, None], actions, positions[1:, None])
    sampled = build_sampled_set(pre, rollout, np.array([0.5, 0.5, 0.0]), 40, rng)
    delta = sampled.next_states[:, 0] - sampled.states[:, 0]
    assert np.array_equal(delta, np.where(sampled.actions == 1, 1.0, -1.0))


def test_apportion_is_exact():
    assert apportion(10, np.array([1, 1, 1])).sum() == 10
    assert apportion(0, np.array([1, 2])).tolist() == [0, 0]
    assert apportion(7, np.array([0, 1, 0])).tolist() == [0, 7, 0]


def test_argmax_without_exploration():
    logits = torch.tensor([[0.0, 3.0, 1.0], [5.0, 0.0, 0.0]])
    assert choose_actions(logits, explore=False).tolist() == [1, 0]


def test_label_sampling_draws_once_per_row_with_softmax_frequencies():
    logits = torch.log(torch.tensor([0.5, 0.3, 0.15, 0.05])).repeat(40_000, 1)
    draws = choose_actions(logits, explore=True, generator=torch.Generator().manual_seed(0))
    assert draws.shape == (40_000,)
    freq = torch.bincount(draws, minlength=4).float() / len(draws)
    torch.testing.assert_close(freq, torch.tensor([0.5, 0.3, 0.15, 0.05]), atol=0.01, rtol=0)
    # rows are independent: different rows with the same logits do not all get the same label
    assert len(set(draws[:100].tolist())) > 1


def test_metrics():
    assert performance(np.array([500.0, 500.0]), 500.0, 20.0) == 1.0
    assert performance(np.array([20.0]), 500.0, 20.0) == 0.0
    assert performance(np.array([260.0]), 500.0, 20.0) == pytest.approx(0.5)


@pytest.mark.parametrize("n", [1, 2, 5, 10, 99, 1000])
def test_held_out_split_is_a_disjoint_cover_with_a_tenth_held(n):
    train, held = held_out_split(n, np.random.default_rng(0))
    assert sorted([*train, *held]) == list(range(n))  # every item once, on one side only
    assert len(held) == (n // 10 if n >= 10 else min(1, n - 1))
    again = held_out_split(n, np.random.default_rng(0))
    assert np.array_equal(again[1], held) and not np.array_equal(
        held_out_split(1000, np.random.default_rng(1))[1], held_out_split(1000, np.random.default_rng(0))[1]
    )


def test_held_out_split_never_takes_every_item_of_a_class_from_training():
    classes = np.array([0] + [1] * 49)  # the rule may ask for class 0: its only item must stay in training
    for seed in range(50):
        plain_train, plain_held = held_out_split(50, np.random.default_rng(seed))
        train, held = held_out_split(50, np.random.default_rng(seed), classes=classes)
        assert 0 in train and sorted([*train, *held]) == list(range(50))
        if 0 not in plain_held:  # the same split as without classes whenever no class is lost
            assert np.array_equal(train, plain_train) and np.array_equal(held, plain_held)
    assert any(0 in held_out_split(50, np.random.default_rng(seed))[1] for seed in range(50))  # the case occurs


def test_selection_compares_the_envs_success_first_then_the_goal_and_the_latest_wins_ties():
    # LunarLander: rollouts that stand on the pad every time but never come to rest do not replace a model whose
    # rollouts came to rest 8 times in 10
    assert not selects(0.0, 1.0, best=(0.8, 0.9))
    assert selects(0.9, 0.1, best=(0.8, 1.0))
    assert selects(0.0, 0.7, best=(0.0, 0.5))  # no rest anywhere: the goal decides
    assert not selects(0.0, 0.4, best=(0.0, 0.5))
    assert selects(0.5, 0.5, best=(0.5, 0.5))  # a tie: the latest cycle
    assert selects(0.0, 0.0, best=(-1.0, -1.0))  # the first cycle is always selected


def test_the_model_is_selected_on_episodes_played_as_lerobot_eval_plays_them():
    # IUPE's rollouts draw (exploration) while lerobot-eval plays the mode: episodes of their own, as many as the
    # rollouts unless told
    assert IUPEConfig().separate_selection_episodes == IUPEConfig().rollout_episodes
    assert IUPEConfig(rollout_episodes=7, selection_episodes=30).separate_selection_episodes == 30
    assert IUPEConfig(selection_episodes=0).separate_selection_episodes == 0  # the paper's rule: the rollouts
    # BCO(α)'s rollouts play the mode, and an exploring policy evaluated by draws plays as its rollouts do: the
    # rollouts themselves are those episodes
    assert IUPEConfig(exploration=False).separate_selection_episodes == 0
    assert IUPEConfig(eval_mode="sample").separate_selection_episodes == 0
    assert IUPEConfig(exploration=False, eval_mode="sample").separate_selection_episodes == 20
    # supervised (BC): the last step unless told (it needs no env), else N episodes of its own
    assert IUPEConfig(supervised=True).separate_selection_episodes == 0
    assert IUPEConfig(supervised=True, selection_episodes=0).separate_selection_episodes == 0
    assert IUPEConfig(supervised=True, selection_episodes=5).separate_selection_episodes == 5
    with pytest.raises(ValueError, match="--policy.selection_episodes"):
        IUPEConfig(selection_episodes=-1)


def test_an_episode_s_windows_repeat_its_first_and_last_frames():
    observations = np.arange(4.0)[:, None]  # s_0 … s_3: three actions
    pairs = Transitions.of_episode(observations, np.arange(3), context=0)
    assert pairs.windows[:, :, 0].tolist() == [[0, 1], [1, 2], [2, 3]] and pairs.context == 0
    windows = Transitions.of_episode(observations, np.arange(3), context=1)
    assert windows.windows[:, :, 0].tolist() == [[0, 0, 1, 2], [0, 1, 2, 3], [1, 2, 3, 3]]
    assert windows.states[:, 0].tolist() == [0, 1, 2] and windows.next_states[:, 0].tolist() == [1, 2, 3]
    assert windows.take(np.array([2])).windows[0, :, 0].tolist() == [1, 2, 3, 3]


def test_frame_differences_are_the_reference_frame_then_each_other_frame_minus_it_in_order():
    values = torch.arange(2 * 5 * 4, dtype=torch.float32).reshape(2, 5, 4) ** 2  # squares: each difference differs
    strided = values[:, :, 1:3]  # a view, as the IDM's windows are
    picked = frame_differences(strided, 2, [0, 2, 4])
    expected = torch.stack([strided[:, 2], strided[:, 0] - strided[:, 2], strided[:, 4] - strided[:, 2]], dim=1)
    assert picked.is_contiguous() and torch.equal(picked, expected)
    every = frame_differences(strided, 1)
    now = strided[:, 1:2]
    assert torch.equal(every, torch.cat([now, strided[:, :1] - now, strided[:, 2:] - now], dim=1))
