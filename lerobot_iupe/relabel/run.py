"""``relabel(cfg)``: check, label, write — under the dataset's one-writer lock."""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_iupe.data.episodes import column_array
from lerobot_iupe.data.readers import FrameReader, action_array, episode_bounds, label_spans
from lerobot_iupe.data.storage import (
    dataset_lock,
    is_dataset,
    read_iupe_meta,
    recover_interrupted_swap,
    resolve_root,
    staged_directory,
    write_iupe_meta,
)
from lerobot_iupe.data.video import default_video_backend
from lerobot_iupe.policy.action_space import feature_names
from lerobot_iupe.policy.algorithm import r_squared
from lerobot_iupe.policy.threads import keep_freed_memory
from lerobot_iupe.relabel.checks import (
    check_has_episodes,
    check_labelable,
    checkpoint_fingerprint,
    label_names,
    load_idm,
)
from lerobot_iupe.relabel.config import RelabelConfig, RelabelReport
from lerobot_iupe.relabel.consistency import pull_toward_observation
from lerobot_iupe.relabel.labelling import (
    assemble_labels,
    assemble_references,
    available_cores,
    gather_on_first,
    label_spans_with_idm,
    last_frame_mask,
    process_group,
)
from lerobot_iupe.relabel.references import (
    joint_references,
    linear_part_references,
    per_dimension_r2,
    thumbnail_references,
)
from lerobot_iupe.relabel.writing import action_feature, copy_dataset, pull_dataset, write_labels


def relabel(cfg: RelabelConfig) -> RelabelReport:
    """Label the dataset ``cfg.dataset`` with the IDM of ``cfg.policy``; write it in place unless ``dry_run``.
    A writing run holds the dataset's lock (``dataset_lock``) from its first check to its swap."""
    cfg.validate()
    rank, world = process_group()
    root = resolve_root(cfg.dataset.repo_id, cfg.dataset.root)
    with contextlib.ExitStack() as stack:
        if rank == 0 and not cfg.dry_run:
            stack.enter_context(dataset_lock(root))
        return _relabel(cfg, root, rank, world)


def _relabel(cfg: RelabelConfig, root: Path, rank: int, world: int) -> RelabelReport:
    torch.set_num_threads(cfg.num_threads)
    keep_freed_memory()  # before the workers fork: they inherit it
    backend = cfg.dataset.video_backend or default_video_backend()
    device = cfg.policy.device
    policy = load_idm(cfg.policy.path, device)
    if rank == 0:
        recover_interrupted_swap(root)
        if not is_dataset(root):
            if root.exists():
                raise FileNotFoundError(
                    f"--dataset.root={root} exists but is not a LeRobot dataset (no meta/info.json)"
                )
            pull_dataset(cfg.dataset.repo_id, root, backend)
        check_has_episodes(root)
    if world > 1:
        dist.barrier()
    dataset = LeRobotDataset(cfg.dataset.repo_id, root=root, video_backend=backend)
    meta = dataset.meta
    keys = check_labelable(policy, meta, cfg.overwrite, cfg.dry_run)
    config = policy.config
    pull = pull_strength(cfg.pull_to_observation, policy, meta)

    start = time.perf_counter()
    bounds = episode_bounds(meta)
    spans = label_spans(bounds, cfg.batch_size, config.idm_window, list(range(rank, len(bounds), world)))
    reader = FrameReader(dataset, keys, config.layout_of(keys), backend)
    workers = max(1, available_cores() // world) if cfg.num_workers is None else cfg.num_workers
    compared = ACTION in meta.features  # the references are only compared with a dataset's own actions
    per_episode = label_spans_with_idm(
        policy, reader, spans, cfg.mode, cfg.seed, device, rank == 0, workers, references=compared
    )
    per_episode = gather_on_first(per_episode, world)
    if world > 1:  # no collective after this; a group left alive aborts the process at exit (gloo's threads)
        dist.destroy_process_group()
    seconds = time.perf_counter() - start
    if per_episode is None:  # not the first process: process 0 writes
        return RelabelReport(
            root, str(cfg.policy.path), cfg.mode, 0, 0, [], [], 0.0, None, seconds,
            processes=world, written=False, first_process=False,
        )  # fmt: skip
    labels, confidence = assemble_labels(per_episode, bounds, config)
    total = len(labels)
    if pull > 0:
        pull_start = time.perf_counter()
        labels = pulled_labels(policy, dataset, labels, confidence, bounds, pull, cfg.seed)
        seconds += time.perf_counter() - pull_start

    agreement, per_dimension, references = None, None, None
    inner = ~last_frame_mask(meta, total)
    if ACTION in meta.features:
        existing = action_array(dataset)
        if config.is_continuous:
            true = existing.reshape(labels.shape)[inner]
            agreement = r_squared(labels[inner], true)
            per_dimension = per_dimension_r2(labels[inner], true)
            if config.joint_idm:
                states = np.concatenate([
                    column_array(dataset.hf_dataset, key).astype(np.float32).reshape(total, -1)
                    for key in config.idm_keys
                ], axis=1)  # fmt: skip
                state_names = feature_names(meta.features.get(OBS_STATE))
                references = joint_references(policy, states, existing, bounds, np.flatnonzero(inner), state_names)
                thumbnails = assemble_references(per_episode, bounds)
                references["thumbnails"] = thumbnail_references(policy, thumbnails, existing, np.flatnonzero(inner))
            elif (linear := assemble_references(per_episode, bounds)) is not None:
                references = linear_part_references(policy, linear, existing, np.flatnonzero(inner))
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
        agreement_per_dimension=per_dimension,
        references=references,
        processes=world,
        continuous=config.is_continuous,
        pull_to_observation=pull,
    )
    if cfg.dry_run:
        return report

    with staged_directory(root, overwrite=True) as staged:
        copy_dataset(root, staged)
        write_labels(staged, labels, action_feature(str(cfg.policy.path), cfg.mode, config, pull))
        iupe_meta = read_iupe_meta(staged)
        iupe_meta.update(
            has_actions=True,
            relabelled_by={
                "checkpoint": str(cfg.policy.path),
                "checkpoint_sha256": checkpoint_fingerprint(cfg.policy.path),
                "mode": cfg.mode,
                "seed": cfg.seed,
                "idm_context": config.idm_context,
                "pull_to_observation": pull,
                "mean_confidence": report.mean_confidence,
                "agreement_with_previous_actions": agreement,
            },
        )
        write_iupe_meta(staged, iupe_meta)
    report.written = True
    return report


def vector_observation_keys(meta) -> list[str]:
    """The dataset's per-frame vector observations (``observation.state``, ``observation.environment_state``, …)."""
    return [
        key for key, feature in meta.features.items()
        if key.startswith("observation.") and feature["dtype"] in ("float32", "float64") and len(feature["shape"]) == 1
    ]  # fmt: skip


def pull_strength(requested: float | None, policy, meta) -> float:
    """``--pull_to_observation`` as given, or its default (``RelabelConfig``): 1 for an IDM of cameras and state
    with continuous actions on a dataset with a vector observation, else 0. A pull that cannot apply is refused."""
    if requested is None:
        applies = policy.config.is_continuous and not policy.config.joint_idm and vector_observation_keys(meta)
        return 1.0 if applies else 0.0
    if requested == 0:
        return 0.0
    if not policy.config.is_continuous:
        raise ValueError(
            "--pull_to_observation applies to continuous actions; this IDM labels discrete ones, so leave it at 0"
        )
    if not vector_observation_keys(meta):
        raise ValueError(
            "--pull_to_observation needs a vector observation (observation.state or observation.environment_state) "
            f"in {meta.root}; this dataset has none, so leave it at 0"
        )
    return requested


def pulled_labels(policy, dataset: LeRobotDataset, labels, spread, bounds, strength: float, seed: int) -> np.ndarray:
    """``--pull_to_observation``: the labels of the frames with a successor moved toward a regression on their
    vector observations (``relabel.consistency``); each episode's last frame then repeats the one before it."""
    keys = vector_observation_keys(dataset.meta)
    observations = np.concatenate(
        [column_array(dataset.hf_dataset, key).astype(np.float32).reshape(len(labels), -1) for key in keys], axis=1
    )
    inner = ~last_frame_mask(dataset.meta, len(labels))
    head = policy.idm_head
    pulled = labels.copy()
    pulled[inner] = pull_toward_observation(
        labels[inner], spread[inner], observations[inner], head.low.cpu().numpy(), head.high.cpu().numpy(),
        strength, seed, fixed_dims=head.binary.cpu().numpy(),
    )  # fmt: skip
    for first, end in bounds:
        if end - first > 1:
            pulled[end - 1] = pulled[end - 2]
    return pulled
