"""IUPE for LeRobot: imitation from state-only demonstrations (Gavenski et al., BMVC 2020)."""

from lerobot_iupe import envs  # noqa: F401  (registers env types and gym ids)
from lerobot_iupe.configuration_iupe import IUPEConfig

__all__ = ["IUPEConfig"]
__version__ = "0.1.0"
