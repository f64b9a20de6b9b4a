"""IUPE for LeRobot: imitation from state-only demonstrations (Gavenski et al., BMVC 2020)."""

from lerobot_iupe import envs  # noqa: F401  (registers env types and gym ids)
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy, make_iupe_pre_post_processors

__all__ = ["IUPEConfig", "IUPEPolicy", "make_iupe_pre_post_processors"]
__version__ = "0.1.0"
