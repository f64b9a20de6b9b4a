"""Every frame of a dataset's camera at the working resolution, decoded once into a uint8 file on disk and read
back memory-mapped, so that training holds a bounded amount of memory whatever the number of frames (as
``datasets`` caches what it prepares). 11,233 frames of two 640×480 cameras are 20.7 GB as decoded; at 96×128 they
are 0.83 GB on disk, of which the kernel keeps in memory what is read.

A cache file is named by what it depends on: the camera's stored files (path, size, modification time), the
dataset's episodes and fps, the working resolution and the decoder. A changed dataset gets a new name and so a new
file; a file is written beside its final name and renamed into place when complete, so a killed build leaves
nothing that a later run would read.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
from pathlib import Path

import numpy as np
from lerobot.utils.constants import HF_LEROBOT_HOME
from tqdm.auto import tqdm

from lerobot_iupe.data.child_processes import exit_with_parent
from lerobot_iupe.data.episodes import EpisodeFrames, open_dataset
from lerobot_iupe.data.storage import pid_alive
from lerobot_iupe.data.video import CameraFrames

log = logging.getLogger("lerobot_iupe")

# Below this many frames a cache is decoded in the calling process: starting worker processes costs more.
IN_PROCESS_FRAMES = 2_000


def cache_dir() -> Path:
    """``$LEROBOT_IUPE_CACHE``, else ``frames_cache`` beside LeRobot's datasets home (``$HF_LEROBOT_HOME/..``)."""
    return Path(os.environ.get("LEROBOT_IUPE_CACHE") or Path(HF_LEROBOT_HOME).parent / "lerobot_iupe_frames")


def cache_key(meta, key: str, shape: tuple[int, int] | None, backend: str) -> str:
    """What the cached frames depend on, hashed (see the module's docstring)."""
    root = Path(meta.root)
    feature = meta.features[key]
    stored = root / "videos" / key if feature["dtype"] == "video" else root / "data"
    files = sorted(p for p in stored.rglob("*") if p.is_file()) if stored.exists() else []
    episodes = meta.episodes
    columns = ["dataset_from_index", "dataset_to_index"]
    if feature["dtype"] == "video":
        columns.append(f"videos/{key}/from_timestamp")
    described = {
        "key": key,
        "shape": list(shape) if shape else None,
        "decoder": CameraFrames.decoder_name(backend, shape, tuple(feature["shape"][:2])),
        "fps": meta.fps,
        "feature": feature,
        "episodes": [[float(v) for v in episodes[c]] for c in columns],
        "files": [[str(p.relative_to(root)), p.stat().st_size, p.stat().st_mtime_ns] for p in files],
    }
    return hashlib.sha256(json.dumps(described, sort_keys=True, default=str).encode()).hexdigest()[:24]


def remove_dead_partials(directory: Path) -> None:
    """Delete the half-written cache files of builds whose process is gone (killed: nothing ever reads them)."""
    for path in directory.glob(".*.partial-*.npy"):
        pid = path.name.rsplit(".partial-", 1)[1].removesuffix(".npy")
        if pid.isdigit() and not pid_alive(int(pid)):
            path.unlink(missing_ok=True)


_readers: dict = {}  # a worker process's open dataset, by (root, key, shape, backend)


def _episode_frames(task: tuple) -> tuple[int, np.ndarray]:
    """One episode's frames (T, C, h, w) uint8 in a worker process."""
    root, repo_id, key, episode, shape, backend = task
    reader = _readers.get((root, key, shape, backend))
    if reader is None:
        reader = _readers[(root, key, shape, backend)] = EpisodeFrames(
            open_dataset(repo_id, root, backend), {key: shape}, backend
        )
    return episode, reader.episode(key, episode)


def cached_frames(
    dataset, key: str, shape: tuple[int, int] | None, backend: str, workers: int | None = None, progress: bool = True
) -> np.ndarray:
    """Every frame of camera ``key`` of ``dataset`` (a ``LeRobotDataset``) as a read-only uint8 memory map
    (N, C, h, w) in the dataset's row order, built on first use (one worker process per core by default, a progress
    bar) and reused while the dataset is unchanged."""
    meta = dataset.meta
    directory = cache_dir()
    name = cache_key(meta, key, shape, backend)
    path = directory / f"{name}.npy"
    if path.exists():
        return np.load(path, mmap_mode="r")
    directory.mkdir(parents=True, exist_ok=True)
    remove_dead_partials(directory)
    bounds = [
        (int(a), int(b))
        for a, b in zip(meta.episodes["dataset_from_index"], meta.episodes["dataset_to_index"], strict=True)
    ]
    total = bounds[-1][1] - bounds[0][0] if bounds else 0
    channels = int(meta.features[key]["shape"][-1])
    height, width = shape or tuple(int(v) for v in meta.features[key]["shape"][:2])
    partial = directory / f".{name}.partial-{os.getpid()}.npy"
    frames = np.lib.format.open_memmap(partial, mode="w+", dtype=np.uint8, shape=(total, channels, height, width))
    workers = workers or min(os.cpu_count() or 1, 8)
    tasks = [(str(meta.root), meta.repo_id, key, e, shape, backend) for e in range(len(bounds))]
    log.info(f"IUPE: caching {total} frames of {key} at {height}×{width} in {path}")
    try:
        with tqdm(total=total, desc=f"caching {key}", unit="frame", disable=not progress) as bar:
            if workers <= 1 or total < IN_PROCESS_FRAMES:
                reader = EpisodeFrames(dataset, {key: shape}, backend)
                results = ((e, reader.episode(key, e)) for e in range(len(bounds)))
                pool = None
            else:  # spawn: the caller may hold torch's thread pools, which a fork would copy half-alive
                pool = multiprocessing.get_context("spawn").Pool(
                    min(workers, len(tasks)), initializer=exit_with_parent, initargs=(os.getpid(),)
                )
                results = pool.imap_unordered(_episode_frames, tasks)
            try:
                for episode, episode_frames in results:
                    first, end = bounds[episode]
                    frames[first - bounds[0][0] : end - bounds[0][0]] = episode_frames
                    bar.update(end - first)
            finally:
                if pool is not None:
                    pool.terminate()
        frames.flush()
        del frames
        os.replace(partial, path)
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    (directory / f"{name}.json").write_text(
        json.dumps({"dataset": str(meta.root), "key": key, "shape": [height, width], "frames": total}) + "\n"
    )
    return np.load(path, mmap_mode="r")
