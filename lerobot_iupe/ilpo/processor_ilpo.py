"""Pre/post-processors of the ILPO policy: LeRobot's defaults (rename → batch → device → normalize), identity
normalization for every feature type (``ObservationPolicyConfig.normalization_mapping``)."""

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from lerobot_iupe.ilpo.configuration_ilpo import ILPOConfig


def make_ilpo_pre_post_processors(
    config: ILPOConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]], PolicyProcessorPipeline[PolicyAction, PolicyAction]
]:
    return make_default_pre_post_processors(config, dataset_stats, normalizer_device=config.device)
