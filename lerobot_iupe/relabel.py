"""Relabel a state-only LeRobot dataset with the inverse dynamics model (IDM) of a trained IUPE checkpoint (a
full IUPE run's, or a ``--policy.supervised=true`` one trained on any labelled dataset of the same robot).

Every frame t with a successor gets ``action = IDM(s_{t-k} … s_{t+1+k})`` (k = the checkpoint's ``idm_context``;
k = 0 is the pair (s_t, s_{t+1})): an action id (int64) for a discrete IDM, a float32 vector with the checkpoint's
action names for a continuous one. The last frame of an episode has no successor; it repeats the label of the
frame before it (an episode of a single frame gets action 0). Episodes are labelled in spans that never cross an
episode, so the labels do not depend on how episodes are shared among processes (``torchrun``). The dataset is
rewritten beside itself and swapped in only when complete (``data.storage.staged_directory``): the original
survives any failure or kill.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import datasets
import numpy as np
import pandas as pd
import torch
import torch.distributed as dist
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.datasets.compute_stats import aggregate_stats, get_feature_stats
from lerobot.datasets.feature_utils import get_hf_features_from_features
from lerobot.datasets.io_utils import load_stats, write_info, write_stats, write_table_one_row_group_per_episode
from lerobot.utils.constants import ACTION
from lerobot.utils.import_utils import get_safe_default_video_backend
from tqdm.auto import tqdm

from lerobot_iupe.data.compat import check_compatible, checkpoint_spec, dataset_spec
from lerobot_iupe.data.readers import (
    FrameReader,
    LabelSpan,
    action_array,
    episode_bounds,
    label_spans,
    prefetched,
    window_indices,
)
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
from lerobot_iupe.policy.algorithm import r_squared

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
    # argmax: the IDM's most likely action (a Gaussian's mean); sample: one draw per frame (seeded by --seed and
    # the episode, so it does not depend on the number of processes).
    mode: str = "argmax"
    seed: int = 0
    # Frames per IDM batch; frames are read (video decoded) in spans of this size, so memory follows the batch,
    # not the dataset.
    batch_size: int = 512
    # Video decoder: "pyav" or "torchcodec"; default: torchcodec where it loads, else pyav (LeRobot's rule).
    video_backend: str | None = None
    device: str = "cpu"
    # CPU threads of the IDM per process. Torch's sums differ in the last bit between thread counts, so a fixed
    # count keeps the labels the same whatever the number of processes; scale out with torchrun (one process per
    # core) rather than threads.
    num_threads: int = 1
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
        if self.num_threads < 1:
            raise ValueError(f"--num_threads must be at least 1, got {self.num_threads}")
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
    action_names: list[str]
    # Discrete: frames per action id. Continuous: the labels' mean per dimension.
    action_summary: list[float]
    # Discrete: the IDM's mean probability of its label. Continuous: its mean predicted standard deviation, in
    # units of the action range (0 = certain).
    mean_confidence: float
    # Against the action the dataset already had (frames with a successor): the share of equal labels (discrete)
    # or R² (continuous).
    agreement_with_existing: float | None
    seconds: float
    processes: int = 1
    written: bool = False
    # Under torchrun only process 0 gathers, writes and reports; the others return a report with this False.
    first_process: bool = True
    continuous: bool = False

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(self.seconds, 1e-9)

    def summary(self) -> str:
        if self.continuous:
            means = zip(self.action_names, self.action_summary, strict=True)
            labels = "mean label " + ", ".join(f"{n}={v:.3f}" for n, v in means)
            labels += f"; mean IDM std {self.mean_confidence:.3f} of the action range"
            agreement = "R² against"
        else:
            total = max(sum(self.action_summary), 1)
            labels = "actions " + ", ".join(f"{a}: {c / total:.1%}" for a, c in enumerate(self.action_summary))
            labels += f"; mean IDM confidence {self.mean_confidence:.3f}"
            agreement = "agreement with"
        processes = f" on {self.processes} processes" if self.processes > 1 else ""
        lines = [
            f"{'wrote' if self.written else 'dry run, nothing written:'} {self.frames} frames of {self.episodes} "
            f"episodes labelled ({self.mode}) in {self.seconds:.1f}s{processes} "
            f"({self.frames_per_second:.0f} frames/s)",
            f"  {labels}",
        ]
        if self.agreement_with_existing is not None:
            lines.append(f"  {agreement} the dataset's existing actions: {self.agreement_with_existing:.4f}")
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
            raise ValueError(
                f"--policy.path={path} is a '{policy_type}' checkpoint; relabelling needs an IUPE one (train an IDM "
                "on labelled data with lerobot-train --policy.type=iupe --policy.supervised=true)"
            )
    try:
        policy = IUPEPolicy.from_pretrained(path)
    except OSError as error:
        raise FileNotFoundError(f"--policy.path={path}: cannot load a checkpoint from there ({error})") from error
    return policy.to(device).eval()


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
    observation key the IDM reads, its shape, fps, and the action space of an ``action`` the dataset already has),
    or when the dataset has actions and replacing them was not asked for. Returns the observation keys."""
    config = policy.config
    for key in config.observation_keys:
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
    return list(config.observation_keys)


# ---------------------------------------------------------------- labelling


def episode_generator(seed: int, episode: int) -> torch.Generator:
    """The draws of one episode (``--mode=sample``): the same whichever process labels it."""
    return torch.Generator().manual_seed(seed * 1_000_003 + episode)


@torch.no_grad()
def label_spans_with_idm(
    policy: IUPEPolicy,
    reader: FrameReader,
    spans: list[LabelSpan],
    mode: str,
    seed: int,
    device: str = "cpu",
    progress: bool = True,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Labels (int64 ids, or float32 vectors) and confidences of the frames of ``spans``, by episode; each
    episode's last frame follows ``LAST_FRAME_RULE``. Reading runs ahead in a background thread."""
    config, head = policy.config, policy.idm_head
    offsets = config.idm_window
    results: dict[int, tuple[list, list]] = {}
    generators: dict[int, torch.Generator] = {}

    def read(span_list):
        for span in span_list:
            yield span, reader.frames(span.episode, span.first, span.lo, span.hi)

    total = sum(span.stop - span.start for span in spans)
    with tqdm(total=total, desc="relabel", unit="frame", unit_scale=True, disable=not progress) as bar:
        for span, frames in prefetched(read(spans)):
            t = np.arange(span.start, span.stop)
            index = window_indices(t, offsets, np.full(len(t), span.first), np.full(len(t), span.last)) - span.lo
            window = frames.to(device)[torch.as_tensor(index, device=device)]
            output = policy.idm_window_output(window).float().cpu()
            generator = generators.setdefault(span.episode, episode_generator(seed, span.episode))
            chosen = head.choose(output, mode == "sample", generator)
            if config.is_continuous:
                _, std = head.mean_and_std(output)
                confidence = 0.5 * std.mean(-1)  # std in units of the action range (scaled space spans 2)
            else:
                confidence = head.likelihood(output, chosen)
            labels, confidences = results.setdefault(span.episode, ([], []))
            labels.append(chosen.numpy())
            confidences.append(confidence.numpy())
            bar.update(len(t))
    return {episode: (np.concatenate(labels), np.concatenate(conf)) for episode, (labels, conf) in results.items()}


def assemble_labels(
    per_episode: dict[int, tuple[np.ndarray, np.ndarray]], bounds: list[tuple[int, int]], config
) -> tuple[np.ndarray, np.ndarray]:
    """One label per frame of the dataset, in frame order (the last frame of an episode: ``LAST_FRAME_RULE``)."""
    total = bounds[-1][1] if bounds else 0
    base = bounds[0][0] if bounds else 0
    if config.is_continuous:
        labels = np.zeros((total - base, config.action_dim), dtype=np.float32)
    else:
        labels = np.zeros(total - base, dtype=np.int64)
    confidence = np.zeros(total - base, dtype=np.float32)
    for episode, (first, end) in enumerate(bounds):
        if episode in per_episode:
            episode_labels, episode_confidence = per_episode[episode]
            labels[first - base : end - 1 - base] = episode_labels.reshape(labels[first - base : end - 1 - base].shape)
            confidence[first - base : end - 1 - base] = episode_confidence
        if end - first > 1:
            labels[end - 1 - base] = labels[end - 2 - base]
            confidence[end - 1 - base] = confidence[end - 2 - base]
    return labels, confidence


def last_frame_mask(meta: LeRobotDatasetMetadata, total_frames: int) -> np.ndarray:
    mask = np.zeros(total_frames, dtype=bool)
    mask[[end - 1 for _, end in episode_bounds(meta)]] = True
    return mask


# ---------------------------------------------------------------- several processes


def process_group() -> tuple[int, int]:
    """(rank, world size): under ``torchrun``/Accelerate (WORLD_SIZE > 1) a gloo process group is joined."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)


def gather_on_first(per_episode: dict, world: int) -> dict | None:
    """Every process's labels on process 0 (None elsewhere)."""
    if world == 1:
        return per_episode
    gathered = [None] * world if dist.get_rank() == 0 else None
    dist.gather_object(per_episode, gathered, dst=0)
    if gathered is None:
        return None
    return {episode: labels for part in gathered for episode, labels in part.items()}


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


def action_feature(checkpoint: str, mode: str, config) -> dict:
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
    rank, world = process_group()
    torch.set_num_threads(cfg.num_threads)
    backend = cfg.video_backend or default_video_backend()
    policy = load_idm(cfg.policy.path, cfg.device)
    root = resolve_root(cfg.dataset.repo_id, cfg.dataset.root)
    if rank == 0:
        recover_interrupted_swap(root)
        if not is_dataset(root):
            if root.exists():
                raise FileNotFoundError(
                    f"--dataset.root={root} exists but is not a LeRobot dataset (no meta/info.json)"
                )
            pull_dataset(cfg.dataset.repo_id, root, backend)
    if world > 1:
        dist.barrier()
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=root, video_backend=backend)
    meta = dataset.meta
    keys = check_labelable(policy, meta, cfg.overwrite, cfg.dry_run)
    config = policy.config

    start = time.perf_counter()
    bounds = episode_bounds(meta)
    spans = label_spans(bounds, cfg.batch_size, config.idm_window, list(range(rank, len(bounds), world)))
    reader = FrameReader(dataset, keys, backend)
    per_episode = label_spans_with_idm(policy, reader, spans, cfg.mode, cfg.seed, cfg.device, progress=rank == 0)
    per_episode = gather_on_first(per_episode, world)
    if world > 1:  # no collective after this; a group left alive aborts the process at exit (gloo's threads)
        dist.destroy_process_group()
    seconds = time.perf_counter() - start
    if per_episode is None:  # not the first process: process 0 writes
        return RelabelReport(
            root, str(cfg.policy.path), cfg.mode, 0, 0, [], [], 0.0, None, seconds, world, False, False
        )
    labels, confidence = assemble_labels(per_episode, bounds, config)
    total = len(labels)

    agreement = None
    inner = ~last_frame_mask(meta, total)
    if ACTION in meta.features:
        existing = action_array(dataset)
        if config.is_continuous:
            agreement = r_squared(labels[inner], existing.reshape(labels.shape)[inner])
        else:
            agreement = float((existing.reshape(total)[inner] == labels[inner]).mean())
    if config.is_continuous:
        summary = labels.mean(axis=0).tolist() if total else [0.0] * config.action_dim
    else:
        summary = np.bincount(labels, minlength=config.n_actions).tolist()
    report = RelabelReport(
        root=root,
        checkpoint=str(cfg.policy.path),
        mode=cfg.mode,
        frames=total,
        episodes=meta.total_episodes,
        action_names=label_names(config),
        action_summary=summary,
        mean_confidence=float(confidence[inner].mean()) if inner.any() else 0.0,
        agreement_with_existing=agreement,
        seconds=seconds,
        processes=world,
        continuous=config.is_continuous,
    )
    if cfg.dry_run:
        return report

    with staged_directory(root, overwrite=True) as staged:
        copy_dataset(root, staged)
        write_labels(staged, labels, action_feature(str(cfg.policy.path), cfg.mode, config))
        iupe_meta = read_iupe_meta(staged)
        iupe_meta.update(
            has_actions=True,
            relabelled_by={
                "checkpoint": str(cfg.policy.path),
                "checkpoint_sha256": checkpoint_fingerprint(cfg.policy.path),
                "mode": cfg.mode,
                "seed": cfg.seed,
                "idm_context": config.idm_context,
                "mean_confidence": report.mean_confidence,
                "agreement_with_previous_actions": agreement,
            },
        )
        write_iupe_meta(staged, iupe_meta)
    report.written = True
    return report
