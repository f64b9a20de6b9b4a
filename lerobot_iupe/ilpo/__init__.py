"""``--policy.type=ilpo``: configuration, policy and processors, as LeRobot's own policy folders export them."""

from lerobot_iupe.ilpo.configuration_ilpo import ILPOConfig
from lerobot_iupe.ilpo.modeling_ilpo import ILPOPolicy
from lerobot_iupe.ilpo.processor_ilpo import make_ilpo_pre_post_processors

__all__ = ["ILPOConfig", "ILPOPolicy", "make_ilpo_pre_post_processors"]
