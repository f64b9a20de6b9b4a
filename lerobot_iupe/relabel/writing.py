"""The labels into a copy of the dataset (video files hard-linked, never written), and pulling a dataset that is
not local yet."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import datasets
import numpy as np
import pandas as pd
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import load_stats, write_info, write_stats, write_table_one_row_group_per_episode
from lerobot.utils.constants import ACTION

from lerobot_iupe.errors import CommandError
from lerobot_iupe.relabel.checks import checkpoint_fingerprint, label_names
from lerobot_iupe.relabel.labelling import LAST_FRAME_RULE


def copy_dataset(root: Path, staged: Path) -> None:
    """Copy a dataset root; its video files are hard-linked (free, and never written here), the rest copied."""
    videos = (root / "videos").resolve()

    def link_or_copy(src: str, dst: str) -> None:
        if Path(src).resolve().is_relative_to(videos):
            try:
                os.link(src, dst)
                return
            except OSError:
                pass
        shutil.copy2(src, dst)

    shutil.copytree(root, staged, copy_function=link_or_copy)


def _rewrite(path: Path, write) -> None:
    """Write a new file and rename it over ``path``: an old inode (maybe shared) is never written into."""
    fresh = path.with_name(path.name + ".new")
    write(fresh)
    os.replace(fresh, path)


def action_feature(checkpoint: str, mode: str, config, pull_to_observation: float = 0.0) -> dict:
    continuous = config.is_continuous
    return {
        "dtype": "float32" if continuous else "int64",
        "shape": (config.action_dim,),
        "names": label_names(config),
        "info": {
            "labelled_by": checkpoint,
            "checkpoint_sha256": checkpoint_fingerprint(checkpoint),
            "mode": mode,
            "idm_context": config.idm_context,
            "last_frame": LAST_FRAME_RULE,
            "pull_to_observation": pull_to_observation,
        },
    }


def write_labels(staged: Path, labels: np.ndarray, feature: dict) -> None:
    """Put ``labels`` as the ``action`` feature of the dataset copy at ``staged``: data files, per-episode stats,
    stats.json and info.json, one data file at a time. (LeRobot's ``modify_features`` refuses to replace an
    existing feature and leaves a new feature without stats, so this pass is written here with LeRobot's own
    writers and its ``get_feature_stats``/``aggregate_stats``.)"""
    meta = LeRobotDatasetMetadata("local/relabel", root=staged)
    info = meta.info
    features = {k: v for k, v in info.features.items() if k != ACTION}
    ordered = {}
    for name, spec in features.items():
        ordered[name] = spec
        if name.startswith("observation."):
            ordered[ACTION] = feature
    ordered.setdefault(ACTION, feature)
    info.features = ordered
    hf_features = get_hf_features_from_features(ordered)
    matrix = labels.reshape(len(labels), -1)
    for path in sorted((staged / "data").glob("*/*.parquet")):
        df = pd.read_parquet(path)
        rows = df["index"].to_numpy()
        df[ACTION] = list(matrix[rows]) if feature["dtype"].startswith("float") else labels[rows]
        table = datasets.Dataset.from_pandas(df[list(hf_features)], features=hf_features, preserve_index=False)
        arrow = table.with_format("arrow")[:]
        _rewrite(path, lambda fresh, arrow=arrow: write_table_one_row_group_per_episode(arrow, fresh))

    episode_stats = []
    for path in sorted((staged / "meta" / "episodes").glob("*/*.parquet")):
        df = pd.read_parquet(path)
        per_episode = [
            get_feature_stats(matrix[a:b].astype(np.float64), axis=0, keepdims=False)
            for a, b in zip(df["dataset_from_index"], df["dataset_to_index"], strict=True)
        ]
        for stat in per_episode[0]:
            df[f"stats/{ACTION}/{stat}"] = [s[stat].tolist() for s in per_episode]
        _rewrite(path, df.to_parquet)
        episode_stats += [{ACTION: s} for s in per_episode]
    stats = load_stats(staged) or {}
    stats[ACTION] = aggregate_stats(episode_stats)[ACTION]
    write_stats(stats, staged)
    write_info(info, staged)


def pull_dataset(repo_id: str, root: Path, video_backend: str) -> None:
    """Download a hub dataset into ``root`` (LeRobot's own download)."""
    try:
        LeRobotDataset(repo_id, root=root, video_backend=video_backend)
    except Exception as error:  # the hub client raises many types; the message is what matters
        shutil.rmtree(root, ignore_errors=True)
        raise CommandError(
            f"--dataset.root={root} does not exist and pulling --dataset.repo_id={repo_id} from the hub failed "
            f"({type(error).__name__}: {error}); check the repo id, HF_ENDPOINT and your token"
        ) from error
