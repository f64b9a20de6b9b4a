"""What ``lerobot-train`` tells the IUPE policy it builds: the rollout env (``--env.*``) and whether the run is a
resume (``--resume=true``) or a new run (``--policy.path`` fine-tunes: new cycle state, today's flags).

LeRobot builds a policy from the dataset alone (``make_policy(cfg.policy, ds_meta=…)``) and passes it neither the
env nor the resume flag, so the policy reads them off the ``TrainPipelineConfig`` of the ``lerobot-train`` call it
is built in, and only there: a policy built from Python (a notebook, another tool) sees nothing of the process's
command line, and is given its env explicitly (``IUPEConfig(env_settings=…)``).
"""

from __future__ import annotations

import inspect
from pathlib import PurePath

from lerobot.configs.train import TrainPipelineConfig

# lerobot/scripts/lerobot_train.py:train(cfg) — found by its file, so ``python -m`` and ``accelerate launch`` count.
_TRAIN_FILE = ("lerobot", "scripts", "lerobot_train.py")


def lerobot_train_config() -> TrainPipelineConfig | None:
    """The config of the ``lerobot-train`` run that is building this policy, or None outside one."""
    frame = inspect.currentframe()
    while frame is not None:
        code = frame.f_code
        if code.co_name == "train" and PurePath(code.co_filename).parts[-3:] == _TRAIN_FILE:
            cfg = frame.f_locals.get("cfg")
            if isinstance(cfg, TrainPipelineConfig):
                return cfg
        frame = frame.f_back
    return None


def resuming() -> bool:
    """Whether this is ``lerobot-train --resume=true`` (continue the saved run exactly), not a new run."""
    cfg = lerobot_train_config()
    return bool(cfg is not None and cfg.resume)


def training_episodes() -> list[int] | None:
    """The episodes the ``lerobot-train`` run building this policy trains on (``--dataset.episodes``); None: all."""
    cfg = lerobot_train_config()
    return None if cfg is None else cfg.dataset.episodes
