"""The action heads of both models: a head turns encoder features into the parameters of a distribution over
actions and knows how to score, draw and summarise actions of that distribution. ``CategoricalHead`` serves discrete
action spaces; ``GaussianHead``, its sibling with the same methods, continuous ones."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_iupe.policy.algorithm import choose_actions


class CategoricalHead(nn.Linear):
    """Logits over ``n_actions`` discrete actions (a linear layer, so checkpoints keep ``<head>.weight/.bias``)."""

    def __init__(self, hidden: int, n_actions: int):
        super().__init__(hidden, n_actions)

    def loss(self, output: Tensor, actions: Tensor, spread: None = None) -> Tensor:
        """Negative log-likelihood of the actions (cross-entropy)."""
        return F.cross_entropy(output, actions)

    def labels(self, output: Tensor, drawn: Tensor, explore: bool) -> tuple[Tensor, None]:
        """What a policy learns from an IDM's ``output``: the drawn ids (the paper's exploration) or the modes."""
        return drawn, None

    def choose(self, output: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        """One action per row: a draw from the distribution when exploring, else its mode (argmax)."""
        return choose_actions(output, explore, generator)

    def mode(self, output: Tensor) -> Tensor:
        return output.argmax(dim=-1)

    def spread(self, output: Tensor, chosen: Tensor) -> float:
        """How far drawn actions are from the mode: the share of non-MAP actions (the paper's self-decaying
        exploration rate)."""
        return float((chosen != self.mode(output)).float().mean())

    def likelihood(self, output: Tensor, chosen: Tensor) -> Tensor:
        """Probability of each chosen action (the labeller's confidence)."""
        return torch.softmax(output.float(), dim=-1).gather(1, chosen[:, None])[:, 0]

    def as_float_action(self, actions: Tensor) -> Tensor:
        """LeRobot's env loop sends float actions of shape (B, action_dim): the id as a float, (B, 1)."""
        return actions.unsqueeze(-1).float()


class GaussianHead(nn.Linear):
    """A diagonal Gaussian over a ``Box`` action of ``action_dim`` dimensions, sibling of ``CategoricalHead``, on
    the action scaled to [-1, 1] by the space's bounds (buffers ``low``/``high``); draws and modes are clipped into
    the bounds. One linear layer holds both parts (checkpoints keep ``<head>.weight/.bias``): its first
    ``action_dim`` rows give the mean, the rest the log standard deviation, per state.

    The two parts are fitted apart. The mean is fitted by squared error through the encoder, exactly as a plain
    regression. The log-std reads the encoder's features detached and is fitted by the Gaussian likelihood of the
    mean's detached residuals. Trained jointly by the likelihood, the std collapsed and starved the mean (SO-101 BC
    per-dimension R² 0.54–0.94 against 0.96–0.99 by squared error; benchmarks/findings.md); apart, the mode is a
    least-squares fit and the spread of draws (exploration, label draws) is the size of the mean's errors.

    ``binary_dims`` are dimensions that take only their bound values (a gripper commanded open or shut): there the
    mean's row is the logit of P(high), fitted by cross-entropy; the mode is the likelier bound and a draw is a
    Bernoulli draw of one, so an action never lands in between (on SO-101 a halfway grasp half-closes the jaws)."""

    LOG_STD_RANGE = (-5.0, 1.0)

    def __init__(
        self, hidden: int, action_dim: int, low: list[float], high: list[float], binary_dims: Sequence[int] = ()
    ):
        super().__init__(hidden, 2 * action_dim)
        self.action_dim = action_dim
        self.register_buffer("low", torch.as_tensor(low, dtype=torch.float32).reshape(action_dim))
        self.register_buffer("high", torch.as_tensor(high, dtype=torch.float32).reshape(action_dim))
        binary = torch.zeros(action_dim, dtype=torch.bool)
        binary[list(binary_dims)] = True
        # Not saved with the weights: config.json's binary_action_dims rebuilds it, and older checkpoints still load.
        self.register_buffer("binary", binary, persistent=False)
        # Modes and draws clipped into the bounds. The linear-first IDM's are not: its bounds come from a few labelled
        # episodes, and a joint that barely moved in them must still be labelled where it goes in others.
        self.clipped = True

    def forward(self, features: Tensor) -> Tensor:
        """[mean, log_std] (B, 2·action_dim); the log-std part sees ``features`` detached."""
        d = self.action_dim
        mean = F.linear(features, self.weight[:d], self.bias[:d])
        log_std = F.linear(features.detach(), self.weight[d:], self.bias[d:])
        return torch.cat([mean, log_std], dim=-1)

    def _scale(self, actions: Tensor) -> Tensor:
        return 2.0 * (actions.float() - self.low) / (self.high - self.low) - 1.0

    def _unscale(self, scaled: Tensor) -> Tensor:
        return self.low + self._share_of_high(scaled) * (self.high - self.low)

    @staticmethod
    def _share_of_high(scaled: Tensor) -> Tensor:
        """Where a scaled value lies between the bounds: 0 at the low one, 1 at the high one (on a binary
        dimension, P(high) of its Bernoulli mean)."""
        return (scaled + 1.0) * 0.5

    def mean_and_std(self, output: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and standard deviation in the scaled space ([-1, 1] per dimension); on a binary dimension those of
        its Bernoulli over the two bounds (mean 2p − 1, std 2·√(p(1 − p)))."""
        mean, log_std = output.float().split(self.action_dim, dim=-1)
        std = log_std.clamp(*self.LOG_STD_RANGE).exp()
        if self.binary.any():
            p = torch.sigmoid(mean)
            mean = torch.where(self.binary, 2.0 * p - 1.0, mean)
            std = torch.where(self.binary, 2.0 * (p * (1.0 - p)).sqrt(), std)
        return mean, std

    def loss(self, output: Tensor, actions: Tensor, spread: Tensor | None = None) -> Tensor:
        """Squared error of the mean plus the negative log-likelihood (constant dropped) of the mean's detached
        residuals under the predicted std; per dimension, scaled space. With ``spread`` (B, action_dim, scaled
        units) the targets are Gaussians N(actions, spread²) and the loss is its expectation over them: what
        training on one draw per target gives on average, without the draw's noise. A binary dimension's loss is
        the cross-entropy of its logit against the target's place between the bounds (0 low, 1 high; a label in
        between is a soft target, the expectation over its draws)."""
        raw_mean, log_std = output.float().split(self.action_dim, dim=-1)
        std = log_std.clamp(*self.LOG_STD_RANGE).exp()
        target = self._scale(actions.reshape(len(raw_mean), -1))
        residual = (target - raw_mean.detach()).square() + (0.0 if spread is None else spread.square())
        gaussian = (target - raw_mean).square() + 0.5 * residual / std.square() + std.log()
        if not self.binary.any():
            return gaussian.mean()
        high_share = self._share_of_high(target).clamp(0.0, 1.0)
        bernoulli = F.binary_cross_entropy_with_logits(raw_mean, high_share, reduction="none")
        return torch.where(self.binary, bernoulli, gaussian).mean()

    def labels(self, output: Tensor, drawn: Tensor, explore: bool) -> tuple[Tensor, Tensor | None]:
        """What a policy learns from an IDM's ``output``: exploring, the IDM's whole distribution (its mode and std,
        so the policy's std carries the labels' uncertainty into its rollouts; on a binary dimension its P(high) as
        a soft target), else its mode."""
        if not explore:
            return drawn, None
        mean, std = self.mean_and_std(output)
        labels = torch.where(self.binary, self._unscale(mean), self._pick(mean, std, explore=False))
        return labels, torch.where(self.binary, 0.0, std)

    def choose(self, output: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        """One action per row (B, action_dim): a draw from the distribution when exploring, else its mode."""
        return self._pick(*self.mean_and_std(output), explore, generator)

    def _pick(self, mean: Tensor, std: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        scaled = mean
        if explore:
            scaled = mean + std * torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
        if self.binary.any():  # the high bound with probability P(high) when drawing, else when it is the likelier
            threshold = (
                torch.rand(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype) if explore else 0.5
            )
            scaled = torch.where(self.binary, torch.where(self._share_of_high(mean) > threshold, 1.0, -1.0), scaled)
        return self._unscale(scaled.clamp(-1.0, 1.0) if self.clipped else scaled)

    def mode(self, output: Tensor) -> Tensor:
        return self.choose(output, explore=False)

    def spread(self, output: Tensor, chosen: Tensor) -> float:
        """How far drawn actions are from the mode: mean Euclidean distance in the scaled space (0 = no
        exploration; it decays as the predicted scale shrinks, like the discrete non-MAP rate)."""
        distance = self._scale(chosen) - self._scale(self.mode(output))
        return float(distance.norm(dim=-1).mean())

    def likelihood(self, output: Tensor, chosen: Tensor) -> Tensor:
        """Density of each chosen action in the scaled space (the labeller's confidence); a binary dimension
        contributes the probability of its chosen bound."""
        mean, std = self.mean_and_std(output)
        scaled = self._scale(chosen)
        density = torch.exp(-0.5 * ((scaled - mean) / std).square()) / (std * (2 * torch.pi) ** 0.5)
        if self.binary.any():
            high_share = self._share_of_high(mean)
            density = torch.where(self.binary, torch.where(scaled > 0, high_share, 1.0 - high_share), density)
        return density.prod(-1)

    def as_float_action(self, actions: Tensor) -> Tensor:
        return actions.float()


def make_action_head(hidden: int, config) -> nn.Module:
    """The head of the config's action space: categorical (``n_actions``) or Gaussian (``action_low/high``)."""
    if config.is_continuous:
        return GaussianHead(
            hidden, len(config.action_low), config.action_low, config.action_high, config.binary_action_dims
        )
    return CategoricalHead(hidden, config.n_actions)
