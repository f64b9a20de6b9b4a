"""What ``lerobot-train`` tells the IUPE policy it builds: the rollout env (``--env.*``) and whether the run is a
resume (``--resume=true``) or a new run (``--policy.path`` fine-tunes: new cycle state, today's flags).

LeRobot builds a policy from the dataset alone (``make_policy(cfg.policy, ds_meta=…)``) and passes it neither the
env nor the resume flag, so the policy reads them off the ``TrainPipelineConfig`` of the ``lerobot-train`` call it
is built in, and only there: a policy built from Python (a notebook, another tool) sees nothing of the process's
command line, and is given its env explicitly (``IUPEConfig(env_settings=…)``). The policy also tells that run's
loader not to decode the cameras, which it reads from its own cache.
"""

from __future__ import annotations

import inspect
from pathlib import PurePath

from lerobot.configs.train import TrainPipelineConfig

from lerobot_iupe.data.loader_view import stop_decoding_cameras

# lerobot/scripts/lerobot_train.py:train(cfg) — found by its file, so ``python -m`` and ``accelerate launch`` count.
_TRAIN_FILE = ("lerobot", "scripts", "lerobot_train.py")


def _train_locals() -> dict:
    """The local variables of the ``lerobot-train`` call building this policy ({} outside one)."""
    frame = inspect.currentframe()
    while frame is not None:
        code = frame.f_code
        if code.co_name == "train" and PurePath(code.co_filename).parts[-3:] == _TRAIN_FILE:
            if isinstance(frame.f_locals.get("cfg"), TrainPipelineConfig):
                return frame.f_locals
        frame = frame.f_back
    return {}


def lerobot_train_config() -> TrainPipelineConfig | None:
    """The config of the ``lerobot-train`` run that is building this policy, or None outside one."""
    return _train_locals().get("cfg")


def read_no_cameras_in_lerobot_train() -> list[str]:
    """Stop the loader of the ``lerobot-train`` run building this policy from decoding cameras: the policy reads
    its frames from the package's cache by the batch's ``index`` (``data.loader_view``). LeRobot builds the policy
    after its datasets and before their loaders, so the loaders take the lean readers. The cameras no longer
    decoded."""
    found = _train_locals()
    datasets = [found.get(name) for name in ("dataset", "eval_dataset")]
    return sorted({key for dataset in datasets if dataset is not None for key in stop_decoding_cameras(dataset)})


def resuming() -> bool:
    """Whether this is ``lerobot-train --resume=true`` (continue the saved run exactly), not a new run."""
    cfg = lerobot_train_config()
    return bool(cfg is not None and cfg.resume)


def training_episodes() -> list[int] | None:
    """The episodes the ``lerobot-train`` run building this policy trains on (``--dataset.episodes``); None: all."""
    cfg = lerobot_train_config()
    return None if cfg is None else cfg.dataset.episodes
