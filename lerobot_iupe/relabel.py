"""Relabel a state-only dataset with the inverse dynamics model (IDM) of a trained IUPE checkpoint.

Every frame t with a successor gets ``action = IDM(s_t, s_{t+1})``. The last frame of an episode has no
successor; it repeats the label of the frame before it (an episode of a single frame gets action 0), which is
what a policy that does not drop last frames should see. The dataset is rewritten beside itself and swapped in
only when complete (``data.storage.staged_directory``): the original survives any failure or kill.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import datasets
import numpy as np
import pandas as pd
import torch
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import load_stats, write_info, write_stats, write_table_one_row_group_per_episode
from lerobot.utils.constants import ACTION
from lerobot.utils.import_utils import get_safe_default_video_backend
from tqdm.auto import tqdm

from lerobot_iupe.data.compat import check_compatible, checkpoint_spec, dataset_spec
from lerobot_iupe.data.readers import Chunk, column_array, episode_bounds, prefetched, state_chunks, video_chunks
from lerobot_iupe.data.storage import (
    DatasetTarget,
    is_dataset,
    read_iupe_meta,
    recover_interrupted_swap,
    resolve_root,
    staged_directory,
    write_iupe_meta,
)
from lerobot_iupe.errors import CommandError
from lerobot_iupe.policy import IUPEPolicy

MODES = ("argmax", "sample")
LAST_FRAME_RULE = "repeats the label of the frame before it (0 for a one-frame episode)"


@dataclass
class CheckpointRef:
    # A trained IUPE checkpoint: .../checkpoints/<step>/pretrained_model (as for lerobot-eval --policy.path).
    path: str | None = None


@dataclass
class RelabelConfig:
    policy: CheckpointRef = field(default_factory=CheckpointRef)
    dataset: DatasetTarget = field(default_factory=DatasetTarget)
    # argmax: the IDM's most likely action; sample: one draw from its softmax per frame (seeded by --seed).
    mode: str = "argmax"
    seed: int = 0
    # Frames per IDM batch; video is decoded in chunks of this size, so memory does not grow with the dataset.
    batch_size: int = 512
    # Video decoder: "pyav" or "torchcodec"; default: torchcodec where it loads, else pyav (LeRobot's rule).
    video_backend: str | None = None
    device: str = "cpu"
    # Replace an `action` feature the dataset already has.
    overwrite: bool = False
    # Label and report statistics, write nothing.
    dry_run: bool = False
    # Push the relabelled dataset with an updated card to the hub as --dataset.repo_id.
    push_to_hub: bool = False

    def validate(self) -> None:
        if not self.policy.path:
            raise ValueError("--policy.path is required: a trained IUPE checkpoint (.../pretrained_model)")
        if self.mode not in MODES:
            raise ValueError(f"--mode={self.mode} is not known; use one of {list(MODES)}")
        if self.batch_size < 1:
            raise ValueError(f"--batch_size must be at least 1, got {self.batch_size}")
        if self.video_backend not in (None, "pyav", "torchcodec"):
            raise ValueError(f"--video_backend={self.video_backend} is not known; use pyav or torchcodec")
        if self.dry_run and self.push_to_hub:
            raise ValueError("--dry_run=true writes nothing, so --push_to_hub=true has nothing to push")


@dataclass
class RelabelReport:
    root: Path
    checkpoint: str
    mode: str
    frames: int
    episodes: int
    action_counts: list[int]
    mean_confidence: float
    # Share of frames (with a successor) whose new label equals the action the dataset already had.
    agreement_with_existing: float | None
    seconds: float
    written: bool = False

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(self.seconds, 1e-9)

    def summary(self) -> str:
        total = max(sum(self.action_counts), 1)
        shares = ", ".join(f"{a}: {c / total:.1%}" for a, c in enumerate(self.action_counts))
        lines = [
            f"{'wrote' if self.written else 'dry run, nothing written:'} {self.frames} frames of {self.episodes} "
            f"episodes labelled ({self.mode}) in {self.seconds:.1f}s ({self.frames_per_second:.0f} frames/s)",
            f"  actions {shares}; mean IDM confidence {self.mean_confidence:.3f}",
        ]
        if self.agreement_with_existing is not None:
            lines.append(f"  agreement with the dataset's existing actions: {self.agreement_with_existing:.4f}")
        return "\n".join(lines)


# ---------------------------------------------------------------- checkpoint and checks


def load_idm(path: str, device: str = "cpu") -> IUPEPolicy:
    """The IUPE policy of a checkpoint directory (or hub model id), in eval mode."""
    local = Path(path)
    if local.exists():
        config_file = local / "config.json"
        if not config_file.exists():
            raise FileNotFoundError(
                f"--policy.path={path} holds no config.json; point it at a checkpoint's pretrained_model directory "
                "(e.g. outputs/train/<run>/checkpoints/last/pretrained_model)"
            )
        policy_type = json.loads(config_file.read_text()).get("type")
        if policy_type != "iupe":
            raise ValueError(f"--policy.path={path} is a '{policy_type}' checkpoint; relabelling needs an IUPE one")
    try:
        policy = IUPEPolicy.from_pretrained(path)
    except OSError as error:
        raise FileNotFoundError(f"--policy.path={path}: cannot load a checkpoint from there ({error})") from error
    if policy.config.is_continuous:
        raise ValueError(
            f"--policy.path={path} predicts continuous actions {policy.config.action_names}; this version writes "
            "discrete labels only (continuous labels come with relabelling any LeRobot dataset)"
        )
    return policy.to(device).eval()


def checkpoint_fingerprint(path: str) -> str:
    """First 16 hex digits of the SHA-256 of the checkpoint's weights ('' when they are not local)."""
    weights = Path(path) / "model.safetensors"
    if not weights.exists():
        return ""
    return hashlib.sha256(weights.read_bytes()).hexdigest()[:16]


def check_labelable(policy: IUPEPolicy, meta: LeRobotDatasetMetadata, overwrite: bool, dry_run: bool) -> str:
    """Raise an error naming both sides when this checkpoint cannot label the dataset (``data.compat``), or when
    the dataset has actions and replacing them was not asked for. Returns the observation key the IDM reads."""
    key = policy.config.observation_key
    check_compatible(checkpoint_spec(policy.config), dataset_spec(meta, key, f"the dataset {meta.root}"))
    if ACTION in meta.features and not (overwrite or dry_run):
        raise FileExistsError(
            f"the dataset {meta.root} already has an '{ACTION}' feature; pass --overwrite=true to replace it "
            "(or --dry_run=true to compare the IDM's labels with it)"
        )
    return key


# ---------------------------------------------------------------- streaming labelling


@torch.no_grad()
def label_chunks(
    policy: IUPEPolicy, chunks: Iterator[Chunk], total_frames: int, mode: str, seed: int, device: str = "cpu"
) -> tuple[np.ndarray, np.ndarray]:
    """IDM labels and their softmax confidence for every frame; last frames follow ``LAST_FRAME_RULE``."""
    labels = np.zeros(total_frames, dtype=np.int64)
    confidence = np.zeros(total_frames, dtype=np.float32)
    generator = torch.Generator().manual_seed(seed)
    with tqdm(total=total_frames, desc="relabel", unit="frame", unit_scale=True) as progress:
        for chunk in chunks:
            frames = chunk.frames.to(device)
            n = len(frames) - 1
            if n > 0:
                output = policy.idm_output(frames[:-1], frames[1:]).float().cpu()
                chosen = policy.idm_head.choose(output, mode == "sample", generator)
                labels[chunk.start : chunk.start + n] = chosen.numpy()
                confidence[chunk.start : chunk.start + n] = policy.idm_head.likelihood(output, chosen).numpy()
            if chunk.ends_episode:
                last = chunk.start + n
                labels[last] = labels[last - 1] if n > 0 else 0
                confidence[last] = confidence[last - 1] if n > 0 else 0.0
                progress.update(n + 1)
            else:
                progress.update(n)
    return labels, confidence


def last_frame_mask(meta: LeRobotDatasetMetadata, total_frames: int) -> np.ndarray:
    mask = np.zeros(total_frames, dtype=bool)
    mask[[end - 1 for _, end in episode_bounds(meta)]] = True
    return mask


# ---------------------------------------------------------------- writing


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


def action_feature(checkpoint: str, mode: str) -> dict:
    return {
        "dtype": "int64",
        "shape": (1,),
        "names": ["action_id"],
        "info": {
            "labelled_by": checkpoint,
            "checkpoint_sha256": checkpoint_fingerprint(checkpoint),
            "mode": mode,
            "last_frame": LAST_FRAME_RULE,
        },
    }


def write_labels(staged: Path, labels: np.ndarray, feature: dict) -> None:
    """Put ``labels`` as the ``action`` feature of the dataset copy at ``staged``: data files, per-episode stats,
    stats.json and info.json. (LeRobot's ``modify_features`` refuses to replace an existing feature and leaves a
    new feature without stats, so this pass is written here with LeRobot's own writers.)"""
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
    for path in sorted((staged / "data").glob("*/*.parquet")):
        df = pd.read_parquet(path)
        df[ACTION] = labels[df["index"].to_numpy()]
        table = datasets.Dataset.from_pandas(df[list(hf_features)], features=hf_features, preserve_index=False)
        arrow = table.with_format("arrow")[:]
        _rewrite(path, lambda fresh, arrow=arrow: write_table_one_row_group_per_episode(arrow, fresh))

    episode_stats = []
    for path in sorted((staged / "meta" / "episodes").glob("*/*.parquet")):
        df = pd.read_parquet(path)
        per_episode = [
            get_feature_stats(labels[a:b, None].astype(np.float64), axis=0, keepdims=False)
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


def default_video_backend() -> str:
    """LeRobot's rule (torchcodec where it loads, else pyav), minus its page-long traceback when it does not."""
    logger = logging.getLogger("lerobot.utils.import_utils")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return get_safe_default_video_backend()
    finally:
        logger.setLevel(level)


def relabel(cfg: RelabelConfig) -> RelabelReport:
    cfg.validate()
    backend = cfg.video_backend or default_video_backend()
    policy = load_idm(cfg.policy.path, cfg.device)
    root = resolve_root(cfg.dataset.repo_id, cfg.dataset.root)
    recover_interrupted_swap(root)
    if not is_dataset(root):
        if root.exists():
            raise FileNotFoundError(f"--dataset.root={root} exists but is not a LeRobot dataset (no meta/info.json)")
        pull_dataset(cfg.dataset.repo_id, root, backend)
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=root, video_backend=backend)
    meta = dataset.meta
    key = check_labelable(policy, meta, cfg.overwrite, cfg.dry_run)

    start = time.perf_counter()
    if meta.features[key]["dtype"] == "video":
        chunks = prefetched(video_chunks(meta, key, cfg.batch_size, backend))
    else:
        chunks = state_chunks(dataset, key, cfg.batch_size)
    total = meta.total_frames
    labels, confidence = label_chunks(policy, chunks, total, cfg.mode, cfg.seed, cfg.device)
    seconds = time.perf_counter() - start

    agreement = None
    if ACTION in meta.features:
        existing = column_array(dataset.hf_dataset, ACTION).reshape(total)
        inner = ~last_frame_mask(meta, total)
        agreement = float((existing[inner] == labels[inner]).mean())
    report = RelabelReport(
        root=root,
        checkpoint=str(cfg.policy.path),
        mode=cfg.mode,
        frames=total,
        episodes=meta.total_episodes,
        action_counts=np.bincount(labels, minlength=policy.config.n_actions).tolist(),
        mean_confidence=float(confidence.mean()),
        agreement_with_existing=agreement,
        seconds=seconds,
    )
    if cfg.dry_run:
        return report

    with staged_directory(root, overwrite=True) as staged:
        copy_dataset(root, staged)
        write_labels(staged, labels, action_feature(str(cfg.policy.path), cfg.mode))
        iupe_meta = read_iupe_meta(staged)
        iupe_meta.update(
            has_actions=True,
            relabelled_by={
                "checkpoint": str(cfg.policy.path),
                "checkpoint_sha256": checkpoint_fingerprint(cfg.policy.path),
                "mode": cfg.mode,
                "seed": cfg.seed,
                "mean_confidence": report.mean_confidence,
                "agreement_with_previous_actions": agreement,
            },
        )
        write_iupe_meta(staged, iupe_meta)
    report.written = True
    return report
