"""IUPE for LeRobot: imitation from state-only demonstrations (Gavenski et al., BMVC 2020), with ILPO (Edwards et al.,
ICML 2019), the paper's other baseline."""

from lerobot_iupe import envs  # noqa: F401  (registers env types and gym ids)
from lerobot_iupe.ilpo import ILPOConfig, ILPOPolicy, make_ilpo_pre_post_processors
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy, make_iupe_pre_post_processors

__all__ = [
    "ILPOConfig",
    "ILPOPolicy",
    "IUPEConfig",
    "IUPEPolicy",
    "make_ilpo_pre_post_processors",
    "make_iupe_pre_post_processors",
]
__version__ = "0.1.0"
