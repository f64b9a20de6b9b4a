"""The encoders of the IUPE policy: state and image encoders with SAGAN-style self-attention, their fusion for
cameras with state, and the camera network of the linear-first IDM. The action heads they feed are in ``heads.py``."""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_iupe.data.observation import ObservationLayout
from lerobot_iupe.policy.algorithm import frame_differences
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
    At 96×128 (then the default working resolution for 640×480) this made the image IDM label 2.6× faster than keys
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
        # oneDNN's convolutions run channels-last on a CPU: 1.1x the forward pass, 1.4x with backward. Without
        # gradients the stem reads the input as written and its output is converted, a third of the values
        # (0.94 against 1.09 ms a 96×128 window of 12 channels; with gradients 1.1x slower, so not then).
        if not x.is_cuda and torch.is_grad_enabled():
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.stem(x)
        if not x.is_cuda:
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.attention1(self.stage1(x))
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
        frames, layout = frames.float(), self.encoder.layout
        cameras = [frame_differences(frames[:, :, layout.columns(i)], 0).view(len(frames), -1, *layout.shapes[i][1:])
                   for i in self.encoder.cameras]  # fmt: skip
        return self.out(self.encoder.encode_parts(cameras, None))
