"""Pre/post-processors of the IUPE policy: LeRobot's defaults (rename → batch → device → normalize).

Normalization is identity for every feature type (see ``IUPEConfig.normalization_mapping``): discrete action
ids must not be rescaled, and states are normalised inside the model."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_iupe.policy.configuration_iupe import IUPEConfig


def make_iupe_pre_post_processors(
    config: IUPEConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]
]:
    return make_default_pre_post_processors(config, dataset_stats, normalizer_device=config.device)
