"""``--policy.type=iupe``: configuration, policy and processors, as LeRobot's own policy folders export them."""

from lerobot_iupe.policy.configuration_iupe import IUPEConfig
from lerobot_iupe.policy.modeling_iupe import IUPEPolicy
from lerobot_iupe.policy.processor_iupe import make_iupe_pre_post_processors

__all__ = ["IUPEConfig", "IUPEPolicy", "make_iupe_pre_post_processors"]
