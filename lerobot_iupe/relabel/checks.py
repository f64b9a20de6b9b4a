"""The checkpoint that labels, and whether it can label a dataset: refused with both sides named, before any
work is done."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.utils.constants import ACTION

from lerobot_iupe.data.compat import check_compatible, checkpoint_spec, dataset_spec
from lerobot_iupe.policy import IUPEPolicy

CHECKPOINT_EXAMPLE = "e.g. outputs/train/<run>/checkpoints/last/pretrained_model"


def load_idm(path: str, device: str = "cpu") -> IUPEPolicy:
    """The IUPE policy of a checkpoint directory (or hub model id), in eval mode."""
    local = Path(path).expanduser()
    if local.exists():
        config_file = local / "config.json"
        if not config_file.exists():
            raise FileNotFoundError(
                f"--policy.path={path} holds no config.json; point it at a checkpoint's pretrained_model directory "
                f"({CHECKPOINT_EXAMPLE})"
            )
        policy_type = json.loads(config_file.read_text()).get("type")
        if policy_type != "iupe":
            raise ValueError(
                f"--policy.path={path} is a '{policy_type}' checkpoint; relabelling needs an IUPE one (train an IDM "
                "on labelled data with lerobot-train --policy.type=iupe --policy.supervised=true)"
            )
    elif path.startswith((".", "/", "~")) or path.count("/") > 1:  # a path, never a hub id (owner/name)
        raise FileNotFoundError(
            f"--policy.path={path} does not exist; point it at a checkpoint's pretrained_model directory "
            f"({CHECKPOINT_EXAMPLE}) or a hub model id"
        )
    try:
        policy = IUPEPolicy.from_pretrained(str(local) if local.exists() else path)
    except (OSError, ValueError) as error:  # the hub client's errors (HFValidationError is a ValueError)
        raise FileNotFoundError(
            f"--policy.path={path} is not a local directory and could not be loaded from the hub "
            f"({type(error).__name__}: {error})"
        ) from error
    return policy.to(device).eval()


def check_has_episodes(root: Path) -> None:
    """Refuse a dataset without episodes (created and finalised empty): nothing to label, and LeRobot would
    look for its missing data files on the hub."""
    info = json.loads((Path(root) / "meta" / "info.json").read_text())
    if not info.get("total_episodes"):
        raise ValueError(
            f"--dataset.root={root} holds no episodes (meta/info.json: total_episodes 0); nothing to label"
        )


def checkpoint_fingerprint(path: str) -> str:
    """First 16 hex digits of the SHA-256 of the checkpoint's weights ('' when they are not local)."""
    weights = Path(path) / "model.safetensors"
    if not weights.exists():
        return ""
    return hashlib.sha256(weights.read_bytes()).hexdigest()[:16]


def label_names(config) -> list[str]:
    return list(config.action_names) if config.is_continuous else ["action_id"]


def check_labelable(policy: IUPEPolicy, meta: LeRobotDatasetMetadata, overwrite: bool, dry_run: bool) -> list[str]:
    """Raise an error naming both sides when this checkpoint cannot label the dataset (``data.compat``: every
    observation key of the checkpoint, its shape, fps, and the action space of an ``action`` the dataset already
    has), or when the dataset has actions and replacing them was not asked for. Returns the observation keys to
    read: those the IDM reads (a linear-first IDM without camera dimensions decodes no camera, but a dataset
    without the cameras the checkpoint was trained with is another robot's)."""
    config = policy.config
    for key in dict.fromkeys([*config.observation_keys, *policy.labelling_keys]):
        check_compatible(checkpoint_spec(config, key), dataset_spec(meta, key, f"the dataset {meta.root}"))
    if ACTION in meta.features:
        if not (overwrite or dry_run):
            raise FileExistsError(
                f"the dataset {meta.root} already has an '{ACTION}' feature; pass --overwrite=true to replace it "
                "(or --dry_run=true to compare the IDM's labels with it)"
            )
        existing = meta.features[ACTION]
        continuous = existing["dtype"].startswith("float")
        if continuous != config.is_continuous or tuple(existing["shape"]) != (config.action_dim,):
            raise ValueError(
                f"the dataset {meta.root} has '{ACTION}' {existing['dtype']} {tuple(existing['shape'])} but the "
                f"checkpoint --policy.path labels {'float32' if config.is_continuous else 'int64'} "
                f"({config.action_dim},); relabel a copy without '{ACTION}' or use a checkpoint of this robot"
            )
        names = existing.get("names")
        if config.is_continuous and isinstance(names, list) and names != list(config.action_names):
            raise ValueError(
                f"the dataset {meta.root} names its actions {names} but the checkpoint --policy.path was trained "
                f"on {list(config.action_names)}; they must be the same actions"
            )
    return list(policy.labelling_keys)
