"""The networks of the IUPE policy: state and image encoders with SAGAN-style self-attention, their fusion for
cameras with state, and the action heads. A head turns encoder features into the parameters of a distribution
over actions and knows how to score, draw and summarise actions of that distribution; ``CategoricalHead`` serves
discrete action spaces, and a head for continuous actions is its sibling with the same methods."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_iupe.data.observation import ObservationLayout
from lerobot_iupe.policy.algorithm import choose_actions
from lerobot_iupe.policy.camera_reference import ThumbnailRidge


class TokenSelfAttention(nn.Module):
    """SAGAN-style self-attention over tokens (B, L, d): x + γ · softmax(QKᵀ/√d) V, γ learned from 0."""

    def __init__(self, dim: int):
        super().__init__()
        self.query, self.key, self.value = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: Tensor) -> Tensor:
        scores = self.query(x) @ self.key(x).transpose(1, 2) / x.shape[-1] ** 0.5
        return x + self.gamma * (torch.softmax(scores, dim=-1) @ self.value(x))


class SpatialSelfAttention(nn.Module):
    """SAGAN self-attention over the positions of a feature map (B, C, H, W), γ learned from 0.

    A map of up to ``MAX_POSITIONS`` positions (a 64×64 maze's first stage, 16×16) is attended in full. A larger
    one is max-pooled to the largest grid of its aspect ratio within ``MAX_POSITIONS``, attended there, and the
    result brought back to the map's size bilinearly before the residual sum: the cost is bounded whatever the
    picture, where a 640×480 camera's first stage (120×160) would need a 19,200 × 19,200 matrix per image (1.5 GB).
    At 96×128 (the default working resolution for 640×480) this made the image IDM label 2.6× faster than keys
    pooled alone with every position querying (benchmarks/relabel.md). SAGAN's scores are unscaled. On a GPU the
    product is ``scaled_dot_product_attention``'s fused kernel; on a CPU the plain product, as that kernel took
    2.4× as long at these head sizes (2–4 channels)."""

    MAX_POSITIONS = 256

    def __init__(self, channels: int):
        super().__init__()
        inner = max(channels // 8, 1)
        self.query, self.key = nn.Conv2d(channels, inner, 1), nn.Conv2d(channels, inner, 1)
        self.value = nn.Conv2d(channels, channels, 1)
        self.gamma = nn.Parameter(torch.zeros(1))

    @classmethod
    def grid(cls, h: int, w: int) -> tuple[int, int]:
        """The (h, w) attended: the map itself up to ``MAX_POSITIONS`` positions, else the largest grid of its
        aspect ratio within them."""
        if h * w <= cls.MAX_POSITIONS:
            return h, w
        scale = (cls.MAX_POSITIONS / (h * w)) ** 0.5
        return max(1, int(h * scale)), max(1, int(w * scale))

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        grid = self.grid(h, w)
        attended = x if grid == (h, w) else F.adaptive_max_pool2d(x, grid)
        q = self.query(attended).flatten(2).transpose(1, 2)
        k = self.key(attended).flatten(2).transpose(1, 2)
        v = self.value(attended).flatten(2).transpose(1, 2)
        if x.is_cuda:
            out = F.scaled_dot_product_attention(q.unsqueeze(1), k.unsqueeze(1), v.unsqueeze(1), scale=1.0).squeeze(1)
        else:
            out = torch.softmax(q @ k.transpose(1, 2), dim=-1) @ v
        out = out.transpose(1, 2).reshape(b, c, *grid)
        if grid != (h, w):
            out = F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False)
        return x + self.gamma * out


class VectorEncoder(nn.Module):
    """One token per state feature (value · w_i + b_i), optional self-attention across features, then an MLP."""

    def __init__(self, n_features: int, token_dim: int, hidden: int, attention: bool):
        super().__init__()
        self.token_weight = nn.Parameter(torch.randn(n_features, token_dim) * 0.5)
        self.token_bias = nn.Parameter(torch.zeros(n_features, token_dim))
        self.attention = TokenSelfAttention(token_dim) if attention else nn.Identity()
        self.mlp = nn.Sequential(
            nn.Linear(n_features * token_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )

    def forward(self, x: Tensor) -> Tensor:
        tokens = x.unsqueeze(-1) * self.token_weight + self.token_bias
        return self.mlp(self.attention(tokens).flatten(1))


class ResidualBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1)
        self.skip = nn.Conv2d(cin, cout, 1, stride) if (cin != cout or stride != 1) else nn.Identity()

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv2(F.relu(self.conv1(x))) + self.skip(x))


class ImageEncoder(nn.Module):
    """Compact residual CNN (CPU-sized at 64×64) with self-attention after the first and second stages."""

    def __init__(self, in_channels: int, width: int, hidden: int, attention: bool):
        super().__init__()
        self.stem = nn.Sequential(nn.Conv2d(in_channels, width, 3, 2, 1), nn.ReLU())
        self.stage1 = ResidualBlock(width, width, 2)
        self.attention1 = SpatialSelfAttention(width) if attention else nn.Identity()
        self.stage2 = ResidualBlock(width, 2 * width, 2)
        self.attention2 = SpatialSelfAttention(2 * width) if attention else nn.Identity()
        self.stage3 = ResidualBlock(2 * width, 2 * width, 1)
        self.pool = nn.AdaptiveAvgPool2d(4)
        self.head = nn.Sequential(nn.Linear(2 * width * 16, hidden), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        if not x.is_cuda:  # oneDNN's convolutions run channels-last: 1.1x the forward pass, 1.4x with backward
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.attention1(self.stage1(self.stem(x)))
        x = self.stage3(self.attention2(self.stage2(x)))
        return self.head(self.pool(x).flatten(1))


class ResNet18Encoder(nn.Module):
    """torchvision ResNet-18 (random init; no download at run time) with self-attention after layer1 and layer2,
    as in the paper's image setting. Meant for GPU runs at larger resolutions (e.g. 224 px)."""

    def __init__(self, in_channels: int, hidden: int, attention: bool):
        super().__init__()
        from torchvision.models import resnet18

        net = resnet18(weights=None)
        if in_channels != 3:
            net.conv1 = nn.Conv2d(in_channels, 64, 7, 2, 3, bias=False)
        self.stem = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool)
        self.layer1, self.layer2, self.layer3, self.layer4 = net.layer1, net.layer2, net.layer3, net.layer4
        self.attention1 = SpatialSelfAttention(64) if attention else nn.Identity()
        self.attention2 = SpatialSelfAttention(128) if attention else nn.Identity()
        self.head = nn.Sequential(nn.Linear(512, hidden), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        x = self.attention1(self.layer1(self.stem(x)))
        x = self.layer4(self.layer3(self.attention2(self.layer2(x))))
        return self.head(torch.flatten(F.adaptive_avg_pool2d(x, 1), 1))


def make_image_encoder(backbone: str, in_channels: int, width: int, hidden: int, attention: bool) -> nn.Module:
    """``backbone`` is validated by the config (``--policy.image_backbone``)."""
    if backbone == "resnet18":
        return ResNet18Encoder(in_channels, hidden, attention)
    return ImageEncoder(in_channels, width, hidden, attention)


class FusedEncoder(nn.Module):
    """Cameras and vectors together: ``frames`` packed frames (B, frames · layout.size, ``ObservationLayout``) are
    cut back into each camera, its frames stacked as channels (B, frames · C, H, W), and the vector keys (B, frames ·
    D); one image encoder per camera (or one shared), one ``VectorEncoder`` for the vectors, their features
    concatenated in key order and mixed by a linear layer."""

    def __init__(self, layout: ObservationLayout, frames: int, config):
        super().__init__()
        hidden = config.hidden_dim
        self.layout, self.frames = layout, frames
        self.cameras = [i for i, visual in enumerate(layout.visual) if visual]
        vector_columns = layout.indices(i for i, visual in enumerate(layout.visual) if not visual)
        self.register_buffer("vector_columns", torch.as_tensor(vector_columns, dtype=torch.long), persistent=False)

        def camera_encoder(i: int) -> nn.Module:
            channels = frames * layout.shapes[i][0]
            return make_image_encoder(config.image_backbone, channels, config.cnn_width, hidden, config.attention)

        shared = config.shared_camera_encoder and len(self.cameras) > 1
        self.camera_encoders = nn.ModuleList(
            [camera_encoder(self.cameras[0])] if shared else [camera_encoder(i) for i in self.cameras]
        )
        self.vector_encoder = (
            VectorEncoder(frames * len(vector_columns), config.token_dim, hidden, config.attention)
            if vector_columns
            else None
        )
        parts = len(self.cameras) + (self.vector_encoder is not None)
        self.mix = nn.Sequential(nn.Linear(parts * hidden, hidden), nn.ReLU())

    def forward(self, x: Tensor) -> Tensor:
        x = x.reshape(len(x), self.frames, self.layout.size)
        cameras = []
        for i in self.cameras:
            c, h, w = self.layout.shapes[i]
            cameras.append(x[:, :, self.layout.columns(i)].reshape(len(x), self.frames * c, h, w))
        vectors = x[:, :, self.vector_columns].flatten(1) if self.vector_encoder is not None else None
        return self.encode_parts(cameras, vectors)

    def encode_parts(self, cameras: list[Tensor], vectors: Tensor | None) -> Tensor:
        """Features of the input already cut: each camera's frames as channels (B, frames · C, H, W), in layout
        order, and the vectors (B, frames · D) (None without vector keys)."""
        features = [self.camera_encoders[min(n, len(self.camera_encoders) - 1)](images)
                    for n, images in enumerate(cameras)]  # fmt: skip
        if self.vector_encoder is not None:
            features.append(self.vector_encoder(vectors))
        return self.mix(torch.cat(features, dim=1))


class CameraIDM(nn.Module):
    """The camera network of the linear-first IDM's camera dimensions (those no state column follows: a gripper
    commanded from a keyboard): frames (B, F, camera values) at t and later frames, read as [x_t, x_j − x_t …]
    (frame differences, as the camera IDM reads them) by ``FusedEncoder``, then one correction per dimension, which
    starts at 0 so that training starts from the state's ridge."""

    def __init__(self, layout: ObservationLayout, dims: int, config):
        super().__init__()
        self.encoder = FusedEncoder(layout, len(config.camera_offsets), config)
        self.out = nn.Linear(config.hidden_dim, dims)
        self.reference = ThumbnailRidge(layout, len(config.camera_offsets), dims)  # what it must beat
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, frames: Tensor) -> Tensor:
        frames = frames.float()
        start = frames[:, :1]
        return self.out(self.encoder(torch.cat([start, frames[:, 1:] - start], dim=1).flatten(1)))


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
