"""The simplest fit of a camera dimension (a gripper commanded from a keyboard, whose opening only a camera shows): a
ridge regression on small grey thumbnails of the camera network's frames. Fitted once on the labelled frames and kept
in the checkpoint, so that ``--dry_run=true`` prints it beside the camera network's labels, as the state's ridge is
printed beside every other dimension."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor, nn

from lerobot_iupe.data.observation import ObservationLayout
from lerobot_iupe.policy.joint_idm import REFERENCE_ALPHA, fit_ridge

THUMBNAIL = (24, 32)  # height, width
# Labelled frames the reference is fitted on at most (evenly spaced): 10,000 thumbnails of three frames are 0.2 GB.
MAX_REFERENCE_ROWS = 10_000


class ThumbnailRidge(nn.Module):
    """a ≈ thumbnails(frames) @ weight + bias for the camera dimensions; frames (B, F, camera values) as the camera
    network reads them (every camera of ``layout`` joined, values in [0, 1])."""

    def __init__(self, layout: ObservationLayout, frames: int, dims: int):
        super().__init__()
        self.shapes = list(layout.shapes)
        features = frames * len(self.shapes) * THUMBNAIL[0] * THUMBNAIL[1]
        self.register_buffer("weight", torch.zeros(features, dims))
        self.register_buffer("bias", torch.zeros(dims))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))

    def thumbnails(self, frames: Tensor) -> Tensor:
        """(B, F × cameras × 24 × 32): each frame's cameras in grey, area-averaged to 32×24."""
        count, steps = frames.shape[:2]
        parts, start = [], 0
        for shape in self.shapes:
            size = int(np.prod(shape))
            grey = frames[:, :, start : start + size].float().reshape(count * steps, *shape).mean(1, keepdim=True)
            parts.append(F.adaptive_avg_pool2d(grey, THUMBNAIL).reshape(count, steps, -1))
            start += size
        return torch.cat(parts, dim=-1).flatten(1)

    def forward(self, frames: Tensor) -> Tensor:
        return self.thumbnails(frames) @ self.weight + self.bias

    @torch.no_grad()
    def fit(self, thumbnails: np.ndarray, actions: np.ndarray, episodes: np.ndarray) -> None:
        """Ridge (``REFERENCE_ALPHA`` on standardised thumbnails, as the state's reference) on labelled frames."""
        halves = np.arange(len(thumbnails)) * 2 // max(len(thumbnails), 1)  # one strength: no folds to choose it on
        weight, bias, _, _ = fit_ridge(thumbnails, actions, episodes, (REFERENCE_ALPHA,), folds=halves)
        self.weight.copy_(torch.as_tensor(weight, dtype=torch.float32))
        self.bias.copy_(torch.as_tensor(bias, dtype=torch.float32))
        self.fitted.fill_(True)


def reference_rows(rows: np.ndarray) -> np.ndarray:
    """At most ``MAX_REFERENCE_ROWS`` of ``rows``, evenly spaced."""
    if len(rows) <= MAX_REFERENCE_ROWS:
        return rows
    return rows[np.linspace(0, len(rows) - 1, MAX_REFERENCE_ROWS).round().astype(np.int64)]
