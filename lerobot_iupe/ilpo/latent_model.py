"""ILPO's networks and the pure functions of its two losses and its latent labelling.

Frames reach these networks flat, as the package packs them (``data.observation``): (B, size) floats, vectors raw
(the authors do not normalise states) and cameras in [0, 1]. The generator predicts the flat difference
s_{t+1} − s_t, so that one generator serves vectors, cameras and both fused.
"""

import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_iupe.policy.heads import make_action_head
from lerobot_iupe.policy.networks import FusedEncoder, make_image_encoder

LEAK = 0.2  # every activation of the authors' networks is a leaky ReLU of this slope


def min_latent_loss(delta: Tensor, predicted: Tensor) -> tuple[Tensor, Tensor]:
    """L_min: per sample the squared error (summed over values) of the latent action that predicts ``delta`` (B, D)
    best among ``predicted`` (B, Z, D), averaged over the batch; and that latent action per sample. Only the winning
    prediction gets a gradient, so each latent action specialises on the transitions it explains."""
    errors = (delta.unsqueeze(1) - predicted).square().sum(-1)
    best, winner = errors.min(dim=1)
    return best.mean(), winner


def expected_state_loss(delta: Tensor, predicted: Tensor, probabilities: Tensor) -> Tensor:
    """L_exp: squared error of the π-weighted prediction Σ_z π(z|s)·G(s, z) (``probabilities`` (B, Z)), with the
    generator's predictions detached: it trains π (and the encoder through π) only, never G."""
    expected = (probabilities.unsqueeze(-1) * predicted.detach()).sum(1)
    return (delta - expected).square().sum(-1).mean()


def best_latent(target: Tensor, candidates: Tensor) -> Tensor:
    """z* = argmin_z ‖target − candidates_z‖₂ per row (``target`` (B, D), ``candidates`` (B, Z, D)); ties go to the
    lowest z."""
    return (target.unsqueeze(1) - candidates).square().sum(-1).argmin(dim=1)


def glorot_(module: nn.Module) -> nn.Module:
    """The authors' layer defaults: Glorot-uniform weights, zero biases."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return module


def make_encoder(config) -> nn.Module:
    """An embedding of flat frames: the authors' MLP (d → w → 2w, leaky ReLU) for vectors; the package's image
    encoder for a lone camera, its fused encoder for cameras with vectors. Output (B, 2w)."""
    layout, width = config.layout, config.embedding_width
    if layout.fused:
        return FusedEncoder(layout, 1, config)
    if config.is_image:
        return CameraEncoder(layout.shapes[0], config)
    return glorot_(nn.Sequential(nn.Linear(layout.size, width), nn.LeakyReLU(LEAK), nn.Linear(width, 2 * width)))


class CameraEncoder(nn.Module):
    """The package's image encoder on one flat camera frame (B, C·H·W), cut back into (B, C, H, W)."""

    def __init__(self, shape: tuple[int, ...], config):
        super().__init__()
        self.shape = tuple(shape)
        self.net = make_image_encoder(config.image_backbone, shape[0], config.cnn_width, config.hidden_dim, False)

    def forward(self, frames: Tensor) -> Tensor:
        return self.net(frames.reshape(len(frames), *self.shape))


class LatentActionEmbedding(nn.Module):
    """One-hot z → Linear → leaky ReLU, as wide as the state embedding it is concatenated with."""

    def __init__(self, n_latent: int, width: int):
        super().__init__()
        self.n_latent = n_latent
        self.linear = glorot_(nn.Linear(n_latent, width))

    def forward(self, z: Tensor) -> Tensor:
        return F.leaky_relu(self.linear(F.one_hot(z, self.n_latent).float()), LEAK)


class LatentPolicyNetwork(nn.Module):
    """E_p, the latent policy π(z|s) (one linear layer on the embedding) and one generator G(E_p(s), z) shared by
    every z: [embedding, z embedding] → 256 → 128 → the flat difference s_{t+1} − s_t."""

    def __init__(self, config):
        super().__init__()
        hidden, self.n_latent = config.hidden_dim, config.n_latent
        self.encoder = make_encoder(config)
        self.policy = glorot_(nn.Linear(hidden, self.n_latent))
        self.latent_embedding = LatentActionEmbedding(self.n_latent, hidden)
        self.generator = glorot_(
            nn.Sequential(
                nn.Linear(2 * hidden, 256), nn.LeakyReLU(LEAK), nn.Linear(256, 128), nn.LeakyReLU(LEAK),
                nn.Linear(128, config.layout.size),
            )
        )  # fmt: skip

    def embed(self, frames: Tensor) -> Tensor:
        """E_p(s) before its activation: where images compare next states (z* of a camera)."""
        return self.encoder(frames)

    def forward(self, frames: Tensor) -> tuple[Tensor, Tensor]:
        """π's logits (B, Z) and G's predicted differences for every z (B, Z, size)."""
        h = F.leaky_relu(self.embed(frames), LEAK)
        batch = len(frames)
        z = torch.arange(self.n_latent, device=frames.device).repeat(batch)
        paired = torch.cat([h.repeat_interleave(self.n_latent, dim=0), self.latent_embedding(z)], dim=1)
        return self.policy(h), self.generator(paired).reshape(batch, self.n_latent, -1)


class ActionRemappingNetwork(nn.Module):
    """π_ξ(a | s, z): its own encoder E_a (fresh weights), the z embedding, then 64 → 32 → the package's action
    head (categorical: cross-entropy; continuous: the Gaussian head, whose mean is a least-squares regression)."""

    def __init__(self, config):
        super().__init__()
        hidden = config.hidden_dim
        self.encoder = make_encoder(config)
        self.latent_embedding = LatentActionEmbedding(config.n_latent, hidden)
        self.mlp = glorot_(nn.Sequential(nn.Linear(2 * hidden, 64), nn.LeakyReLU(LEAK), nn.Linear(64, 32)))
        self.head = make_action_head(32, config)

    def forward(self, frames: Tensor, z: Tensor) -> Tensor:
        """The action head's distribution parameters for (s, z)."""
        h = torch.cat([F.leaky_relu(self.encoder(frames), LEAK), self.latent_embedding(z)], dim=1)
        return self.head(F.leaky_relu(self.mlp(h), LEAK))
