"""Continuous actions: the sampling rule on action cells, the Gaussian head's draws, the continuous envs."""

import numpy as np
import pytest
import torch

from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.policy.algorithm import ActionCells, build_sampled_set, r_squared, success_action_distribution
from lerobot_iupe.policy.heads import CategoricalHead, GaussianHead

LOW, HIGH = np.array([-1.0, 0.0]), np.array([1.0, 2.0])
CORNERS = np.array([[-0.9, 0.1], [0.9, 0.1], [-0.9, 1.9], [0.9, 1.9]])


def clustered_actions(counts, rng, tag: float) -> Transitions:
    """Actions scattered tightly around the four corners, ``counts[i]`` around corner i."""
    actions = np.concatenate([CORNERS[i] + rng.normal(0, 0.02, (n, 2)) for i, n in enumerate(counts)])
    states = np.stack([np.full(len(actions), tag), np.arange(len(actions), dtype=float)], axis=1)
    return Transitions.pairs(states, actions.astype(np.float32), states + 1.0)


@pytest.fixture
def cells_and_pre():
    rng = np.random.default_rng(0)
    pre = clustered_actions([200, 60, 40, 100], rng, tag=0.0)
    return ActionCells.fit(pre.actions, 4, LOW, HIGH, seed=0), pre


def test_kmeans_cells_find_the_clusters_and_are_seeded(cells_and_pre):
    cells, pre = cells_and_pre
    classes = cells.assign(pre.actions)
    # each corner's actions share one cell and the four corners get four different cells
    corner_cells = [set(classes[a:b]) for a, b in ((0, 200), (200, 260), (260, 300), (300, 400))]
    assert all(len(c) == 1 for c in corner_cells) and len(set.union(*corner_cells)) == 4
    again = ActionCells.fit(pre.actions, 4, LOW, HIGH, seed=0)
    np.testing.assert_array_equal(again.centres, cells.centres)
    assert ActionCells.fit(pre.actions[:3], 16, LOW, HIGH, seed=0).k == 3  # no more cells than distinct actions


def test_continuous_r_zero_gives_exactly_the_pre_demonstrations(cells_and_pre):
    cells, pre = cells_and_pre
    successful = clustered_actions([30, 10, 0, 0], np.random.default_rng(1), tag=1.0)
    p = np.zeros(cells.k)
    sampled = build_sampled_set(
        pre,
        successful,
        p,
        len(pre),
        np.random.default_rng(0),
        cells.assign(pre.actions),
        cells.assign(successful.actions),
    )
    assert sorted(map(tuple, sampled.states)) == sorted(map(tuple, pre.states))


def test_continuous_shares_follow_eq1_on_cells_and_keep_every_pre_cell(cells_and_pre):
    cells, pre = cells_and_pre
    rng = np.random.default_rng(1)
    successful = clustered_actions([30, 10, 0, 0], rng, tag=1.0)
    episodes = [successful.actions[:30], successful.actions[30:], clustered_actions([0, 0, 5, 5], rng, 2).actions]
    classes = [cells.assign(a) for a in episodes]
    p = success_action_distribution(classes, np.array([True, True, False]), cells.k)
    assert p.sum() == pytest.approx(2 / 3)  # r: two of three rollouts succeeded
    size = 300
    sampled = build_sampled_set(
        pre, successful, p, size, np.random.default_rng(0), cells.assign(pre.actions), cells.assign(successful.actions)
    )
    assert len(sampled) == size
    from_success = sampled.states[:, 0] == 1.0
    assert from_success.sum() == round(2 / 3 * size)
    # the successful share per cell ∝ P(cell|E): corner 0 cell gets 1/2, corner 1 cell 1/2 (each run is one cell)
    success_cells = np.bincount(cells.assign(sampled.actions[from_success]), minlength=cells.k)
    assert sorted(success_cells[success_cells > 0].tolist()) == [100, 100]
    # every cell of I_pre keeps at least one sample while r < 1
    pre_cells = set(cells.assign(sampled.actions[~from_success]).tolist())
    assert pre_cells == set(range(cells.k))


def gaussian_head(mean, log_std) -> tuple[GaussianHead, torch.Tensor]:
    head = GaussianHead(hidden=1, action_dim=2, low=LOW.tolist(), high=HIGH.tolist())
    output = torch.tensor([[*mean, *log_std]], dtype=torch.float32).repeat(20000, 1)
    return head, output


def test_gaussian_draws_follow_the_predicted_distribution():
    # scaled mean (0.2, -0.3), std (0.1, 0.05): in action units mean (0.2, 0.7), std (0.1, 0.05)
    head, output = gaussian_head([0.2, -0.3], np.log([0.1, 0.05]))
    draws = head.choose(output, explore=True, generator=torch.Generator().manual_seed(0))
    np.testing.assert_allclose(draws.mean(0).numpy(), [0.2, 0.7], atol=0.005)
    np.testing.assert_allclose(draws.std(0).numpy(), [0.1, 0.05], rtol=0.03)
    np.testing.assert_allclose(head.mode(output)[0].numpy(), [0.2, 0.7], atol=1e-6)
    # mean distance of a draw from the mode: E|z| of a centred Gaussian with these scales (scaled units)
    expected = np.linalg.norm(np.random.default_rng(1).normal(0, [0.1, 0.05], (1_000_000, 2)), axis=1).mean()
    assert head.spread(output, draws) == pytest.approx(expected, rel=0.02)
    assert head.spread(output, head.mode(output)) == 0.0


def test_gaussian_draws_and_modes_stay_within_the_bounds():
    head, output = gaussian_head([3.0, -0.95], [0.0, 0.0])
    draws = head.choose(output, explore=True, generator=torch.Generator().manual_seed(0))
    assert (draws >= torch.tensor(LOW, dtype=torch.float32)).all()
    assert (draws <= torch.tensor(HIGH, dtype=torch.float32)).all()
    np.testing.assert_allclose(head.mode(output)[0].numpy(), [1.0, 0.05], atol=1e-6)


def test_gaussian_loss_is_minimised_at_the_data_mean_and_spread():
    rng = np.random.default_rng(0)
    actions = torch.tensor(np.stack([rng.normal(0.3, 0.2, 5000), rng.normal(1.5, 0.1, 5000)], 1), dtype=torch.float32)
    head = GaussianHead(hidden=1, action_dim=2, low=LOW.tolist(), high=HIGH.tolist())
    # scaled: mean (0.3, 0.5), std (0.2, 0.1)
    best = torch.tensor([[0.3, 0.5, np.log(0.2), np.log(0.1)]], dtype=torch.float32).repeat(5000, 1)
    for shifted in ([0.4, 0.5, np.log(0.2), np.log(0.1)], [0.3, 0.5, np.log(0.4), np.log(0.1)]):
        worse = torch.tensor([shifted], dtype=torch.float32).repeat(5000, 1)
        assert head.loss(best, actions) < head.loss(worse, actions)


def test_gaussian_std_learns_from_detached_features_and_never_moves_the_mean():
    torch.manual_seed(0)
    head = GaussianHead(hidden=3, action_dim=2, low=LOW.tolist(), high=HIGH.tolist())
    features = torch.randn(8, 3, requires_grad=True)
    output = head(features)
    # a gradient on the log-std reaches the head's log-std rows only: not the features, not the mean rows
    output[:, 2:].sum().backward()
    assert features.grad is None or not features.grad.any()
    assert not head.weight.grad[:2].any() and head.weight.grad[2:].any()
    # the mean's gradient is that of the squared error alone, whatever the std
    actions = torch.tensor([[0.5, 1.0]] * 8)
    for log_std in (-4.0, 0.5):
        out = torch.cat([output[:, :2].detach(), torch.full((8, 2), log_std)], 1).requires_grad_(True)
        head.loss(out, actions).backward()
        mse = torch.cat([output[:, :2].detach(), torch.zeros(8, 2)], 1).requires_grad_(True)
        (head._scale(actions) - mse[:, :2]).square().mean().backward()
        torch.testing.assert_close(out.grad[:, :2], mse.grad[:, :2])


def test_gaussian_labels_with_a_spread_train_as_draws_do_on_average_without_their_noise():
    """Exploring, a policy learns from the IDM's Gaussian (mode and std): its gradient is the average of single
    draws' gradients, and its loss theirs less the draws' own variance (a constant)."""
    torch.manual_seed(0)
    head = GaussianHead(hidden=1, action_dim=2, low=LOW.tolist(), high=HIGH.tolist())
    idm = torch.tensor([[0.2, -0.3, np.log(0.2), np.log(0.1)]]).repeat(4, 1)
    labels, spread = head.labels(idm, head.choose(idm, explore=True), explore=True)
    torch.testing.assert_close(labels, head.mode(idm))
    torch.testing.assert_close(spread, torch.tensor([[0.2, 0.1]]).repeat(4, 1))
    policy = torch.tensor([[0.1, -0.2, np.log(0.3), np.log(0.3)]], requires_grad=True)
    expected = head.loss(policy.repeat(4, 1), labels, spread)
    (grad_expected,) = torch.autograd.grad(expected, policy)
    draws = head.choose(idm[:1].repeat(200_000, 1), explore=True, generator=torch.Generator().manual_seed(1))
    sampled = head.loss(policy.repeat(len(draws), 1), draws)
    (grad_sampled,) = torch.autograd.grad(sampled, policy)
    assert float(sampled) == pytest.approx(float(expected + spread.square().mean()), abs=2e-3)
    torch.testing.assert_close(grad_sampled, grad_expected, atol=2e-3, rtol=0)
    assert head.labels(idm, labels, explore=False)[1] is None  # not exploring: the mode, exactly


def fit(encoder: torch.nn.Module, head: GaussianHead, x: torch.Tensor, y: torch.Tensor, steps: int) -> None:
    """Adam on the head's loss, batches of 128 drawn from (x, y)."""
    optimizer = torch.optim.Adam([*encoder.parameters(), *head.parameters()], 1e-3)
    for _ in range(steps):
        idx = torch.randint(0, len(x), (128,))
        loss = head.loss(head(encoder(x[idx])), y[idx])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def test_gaussian_head_mean_fits_a_regression_with_a_hard_dimension_and_uneven_noise():
    """The mean must fit as a plain regression does where the likelihood alone starves it: one dimension is a
    chirp (hard to fit) and the other's noise is 15x larger in half of the inputs. Trained by the joint likelihood,
    the same network reached R² 0.52-0.72 on the chirp (4 seeds); the mode must reach 0.95 on both dimensions,
    and the predicted std must follow the noise."""
    from lerobot_iupe.policy.networks import VectorEncoder

    torch.manual_seed(0)
    rng = np.random.default_rng(0)

    def data(n):
        x = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
        mean = np.stack([0.8 * np.sin(4.5 * (x[:, 0] + 1) ** 2), 0.8 * np.sin(3 * x[:, 1])], 1)
        noise = np.stack([np.full(n, 0.01), np.where(x[:, 0] > 0, 0.15, 0.01)], 1)
        return torch.tensor(x), mean, torch.tensor(mean + noise * rng.normal(size=mean.shape), dtype=torch.float32)

    x, _, y = data(4000)
    test_x, test_mean, _ = data(2000)
    encoder, head = VectorEncoder(2, 16, 64, attention=True), GaussianHead(64, 2, [-1.0, -1.0], [1.0, 1.0])
    fit(encoder, head, x, y, steps=2500)
    with torch.no_grad():
        output = head(encoder(test_x))
    predicted = head.mode(output).numpy()
    r2 = 1 - ((predicted - test_mean) ** 2).sum(0) / ((test_mean - test_mean.mean(0)) ** 2).sum(0)
    assert (r2 > 0.95).all(), r2
    _, std = head.mean_and_std(output)
    noisy = test_x[:, 0] > 0
    assert std[noisy, 1].median() > 3 * std[~noisy, 1].median()


@pytest.mark.parametrize("kind", ["categorical", "gaussian", "gaussian with a binary dimension"])
def test_categorical_and_gaussian_heads_keep_one_contract(kind):
    """The loop calls both heads alike: on a distribution peaked at known actions, each method must say so."""
    if kind == "categorical":
        head, best, other = CategoricalHead(4, 3), torch.tensor([2, 0]), torch.tensor([1, 1])
        peaked = torch.tensor([[0.0, 0.0, 5.0], [5.0, 0.0, 0.0]])
        wide = torch.zeros(2, 3)
    elif kind == "gaussian with a binary dimension":  # dimension 1 is a logit of P(high) between the bounds 0 and 1
        head = GaussianHead(4, 2, low=[-2.0, 0.0], high=[2.0, 1.0], binary_dims=[1])
        best, other = torch.tensor([[1.0, 1.0], [-1.0, 0.0]]), torch.tensor([[-1.5, 0.0], [1.5, 1.0]])
        peaked = torch.tensor([[0.5, 6.0, -3.0, -3.0], [-0.5, -6.0, -3.0, -3.0]])
        wide = torch.tensor([[0.5, 0.0, 0.5, 0.5], [-0.5, 0.0, 0.5, 0.5]])
    else:
        head = GaussianHead(4, 2, low=[-2.0, 0.0], high=[2.0, 1.0])  # scaled: a = low + (s + 1)(high - low)/2
        best, other = torch.tensor([[1.0, 0.25], [-1.0, 0.75]]), torch.tensor([[-1.5, 0.9], [1.5, 0.1]])
        peaked = torch.tensor([[0.5, -0.5, -3.0, -3.0], [-0.5, 0.5, -3.0, -3.0]])
        wide = torch.tensor([[0.5, -0.5, 0.5, 0.5], [-0.5, 0.5, 0.5, 0.5]])
    assert torch.allclose(head.mode(peaked).float(), best.float())
    assert torch.equal(head.choose(peaked, explore=False), head.mode(peaked))
    draw = lambda seed: head.choose(wide, explore=True, generator=torch.Generator().manual_seed(seed))  # noqa: E731
    assert torch.equal(draw(0), draw(0)) and not all(torch.equal(draw(0), draw(s)) for s in range(1, 6))
    assert head.spread(peaked, head.mode(peaked)) == 0.0 < max(head.spread(wide, draw(s)) for s in range(5))
    assert (head.likelihood(peaked, best) > head.likelihood(peaked, other)).all()
    assert head.loss(peaked, best) < head.loss(peaked, other)
    labels, spread = head.labels(peaked, best, explore=False)
    assert torch.equal(labels, best) and spread is None
    action = head.as_float_action(best)
    assert action.dtype == torch.float32 and action.shape == (2, 1 if kind == "categorical" else 2)


def test_a_binary_dimension_is_a_bernoulli_between_its_bounds():
    """SO-101's grasp is commanded open (1) or shut (0): its mode and draws must be one of the bounds, drawn as
    often as the predicted P(high); the loss must be lowest at the data's share of highs; the labels a policy
    learns from when exploring carry that share as a soft target."""
    head = GaussianHead(hidden=1, action_dim=2, low=[-1.0, 0.0], high=[1.0, 1.0], binary_dims=[1])
    logit = float(np.log(0.7 / 0.3))
    output = torch.tensor([[0.2, logit, np.log(0.1), 0.0]], dtype=torch.float32).repeat(20000, 1)
    np.testing.assert_allclose(head.mode(output)[0].numpy(), [0.2, 1.0], atol=1e-6)
    draws = head.choose(output, explore=True, generator=torch.Generator().manual_seed(0))
    assert set(draws[:, 1].unique().tolist()) == {0.0, 1.0}
    assert float(draws[:, 1].mean()) == pytest.approx(0.7, abs=0.01)
    assert float(draws[:, 0].std()) == pytest.approx(0.1, rel=0.03)  # the Gaussian dimension is unchanged
    np.testing.assert_allclose(head.likelihood(output[:2], torch.tensor([[0.2, 1.0], [0.2, 0.0]]))[1:] * 0.1 * (
        2 * np.pi) ** 0.5, [0.3], rtol=1e-5)  # fmt: skip
    labels, spread = head.labels(output[:1], draws[:1], explore=True)
    np.testing.assert_allclose(labels.numpy(), [[0.2, 0.7]], atol=1e-5)
    assert float(spread[0, 1]) == 0.0 and float(spread[0, 0]) == pytest.approx(0.1, rel=1e-5)
    targets = torch.tensor([[0.2, 1.0]] * 7 + [[0.2, 0.0]] * 3)
    losses = {
        shift: float(head.loss(torch.tensor([[0.2, logit + shift, np.log(0.1), 0.0]]).repeat(10, 1), targets))
        for shift in (-0.5, 0.0, 0.5)
    }
    assert losses[0.0] < losses[-0.5] and losses[0.0] < losses[0.5]


def test_a_binary_dimension_learns_a_switch_and_plays_only_its_bounds():
    """A grasp that switches at x = 0.1: fitted by squared error the mode blurs into half-closed values around the
    switch (the Gaussian head without binary dimensions fails this); as a binary dimension every mode is a bound
    and away from the switch the right one."""
    from lerobot_iupe.policy.networks import VectorEncoder

    torch.manual_seed(0)
    x = torch.rand(4000, 1) * 2 - 1
    y = (x < 0.1).float()
    encoder, head = VectorEncoder(1, 16, 64, attention=False), GaussianHead(64, 1, [0.0], [1.0], binary_dims=[0])
    fit(encoder, head, x, y, steps=600)
    test = torch.linspace(-1, 1, 401)[:, None]
    with torch.no_grad():
        mode = head.mode(head(encoder(test)))[:, 0]
    assert set(mode.unique().tolist()) <= {0.0, 1.0}
    away = (test[:, 0] - 0.1).abs() > 0.05
    assert torch.equal(mode[away], (test[away, 0] < 0.1).float())


def test_r_squared():
    true = np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 5.0]])
    assert r_squared(true, true) == 1.0
    assert r_squared(np.tile(true.mean(0), (3, 1)), true) == pytest.approx(0.0)


def test_bad_continuous_settings_are_refused_naming_the_flag():
    from lerobot.configs import FeatureType, PolicyFeature

    from lerobot_iupe.envs.configs import SO101PickPlaceEnvConfig
    from lerobot_iupe.policy import IUPEConfig

    with pytest.raises(ValueError, match="--policy.action_cells must be at least 1"):
        IUPEConfig(action_cells=0)
    with pytest.raises(ValueError, match="--policy.action_low and --policy.action_high must be given together"):
        IUPEConfig(action_low=[-1.0, -1.0], action_high=[1.0])
    with pytest.raises(ValueError, match=r"--policy.binary_action_dims must list distinct action dimensions"):
        IUPEConfig(binary_action_dims=[3, 3])
    with pytest.raises(
        ValueError, match=r"--policy.binary_action_dims names dimension\(s\) \[4\], but the action has 4"
    ):
        IUPEConfig(
            action_low=[-1.0] * 3 + [0.0], action_high=[1.0] * 4, binary_action_dims=[4]
        ).check_binary_action_dims()
    with pytest.raises(ValueError, match=r"--policy.binary_action_dims=\[0\] applies to continuous \(Box\) actions"):
        IUPEConfig(n_actions=3, binary_action_dims=[0]).check_binary_action_dims()
    for share in (0.0, 1.5):
        with pytest.raises(ValueError, match=r"--policy.max_success_share must be in \(0, 1\]"):
            IUPEConfig(max_success_share=share)
    with pytest.raises(ValueError, match="--env.action_scale must be positive"):
        SO101PickPlaceEnvConfig(action_scale=0.0).validate()
    with pytest.raises(ValueError, match="--env.relative_positions=true extends environment_state, which"):
        SO101PickPlaceEnvConfig(relative_positions=True, image_obs=True).validate()
    state = PolicyFeature(type=FeatureType.STATE, shape=(3,))
    image = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 8, 8))
    unknown = IUPEConfig(input_features={"observation.state": state}, observation_keys=["observation.nothing"])
    with pytest.raises(ValueError, match=r"--policy.observation_keys names \['observation.nothing'\]"):
        unknown.validate_features()
    small = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 4, 4))
    shared = IUPEConfig(
        input_features={"observation.state": state, "observation.images.a": image, "observation.images.b": small},
        shared_camera_encoder=True,
    )
    with pytest.raises(ValueError, match="--policy.shared_camera_encoder=true needs cameras of one size"):
        shared.validate_features()
    outside = IUPEConfig(
        input_features={"observation.state": state, "observation.image": image},
        observation_keys=["observation.image"],
        idm_observation_keys=["observation.state"],
    )
    with pytest.raises(ValueError, match=r"--policy.idm_observation_keys=\['observation.state'\] must name"):
        outside.validate_features()
