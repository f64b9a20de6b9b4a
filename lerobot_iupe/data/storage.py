"""Where datasets live and how they are written: targets and roots, the package's own metadata file, and
write-new-then-swap so that an existing dataset is never left half-written or damaged."""

from __future__ import annotations

import ctypes
import errno
import fcntl
import json
import os
import shutil
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from lerobot.utils.constants import HF_LEROBOT_HOME

from lerobot_iupe.errors import CommandError


@dataclass
class DatasetTarget:
    """``--dataset.*`` of the package's commands: which dataset to write, relabel or push."""

    # The dataset's repo id (owner/name; "local/<name>" for a dataset that stays on disk).
    repo_id: str = "local/iupe-demos"
    # Local directory of the dataset; defaults to $HF_LEROBOT_HOME/<repo_id>.
    root: str | None = None
    # Create the hub repository as private when pushing.
    private: bool = False


@dataclass
class WrittenDataset(DatasetTarget):
    """``--dataset.*`` of a command that writes a dataset (collect, relabel)."""

    # Push the finished dataset and its card to the hub as --dataset.repo_id (HF_ENDPOINT, your token).
    push_to_hub: bool = False


def is_dataset(root: str | Path) -> bool:
    """Whether ``root`` holds a LeRobot dataset (its ``meta/info.json``)."""
    return (Path(root) / "meta" / "info.json").exists()


# LeRobot's DatasetInfo drops unknown keys of meta/info.json, so the package keeps its own file beside it.
IUPE_META_PATH = "meta/iupe.json"


def resolve_root(repo_id: str, root: str | Path | None) -> Path:
    """LeRobot's default: ``$HF_LEROBOT_HOME/<repo_id>`` when no root is given."""
    return Path(root) if root is not None else HF_LEROBOT_HOME / repo_id


def read_iupe_meta(root: str | Path) -> dict:
    """The package's metadata of a dataset (env settings, agent, seeds, layouts); ``{}`` if absent."""
    path = Path(root) / IUPE_META_PATH
    return json.loads(path.read_text()) if path.exists() else {}


def write_iupe_meta(root: str | Path, meta: dict) -> None:
    path = Path(root) / IUPE_META_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def check_writable(root: Path, overwrite: bool) -> None:
    """Refuse an existing root unless overwriting was asked for — before any work is done."""
    if root.exists() and not overwrite:
        raise FileExistsError(
            f"--dataset.root={root} already exists; choose another root, or pass --overwrite=true to replace it "
            "(the old dataset is kept until the new one is complete)"
        )


@contextmanager
def staged_directory(final: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a fresh sibling directory to build into; on success swap it in for ``final``.

    On any exception the staged directory is removed and ``final`` is untouched. The swap is one atomic exchange
    of the two directories where Linux offers it, so a process killed at any moment leaves the old or the new
    dataset at ``final``; elsewhere it is two renames, and a kill between them leaves only the hidden old copy.
    Hidden siblings named after the dead process are put back or removed by the next run on ``final``
    (``recover_interrupted_swap``)."""
    recover_interrupted_swap(final)
    check_writable(final, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    token = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
    staged = final.parent / f".{final.name}.partial-{token}"
    try:
        yield staged
    except BaseException:
        shutil.rmtree(staged, ignore_errors=True)
        raise
    if final.exists() and exchange_paths(staged, final):
        shutil.rmtree(staged, ignore_errors=True)  # it now holds the old dataset
        return
    backup = final.parent / f".{final.name}.old-{token}"
    if final.exists():
        os.rename(final, backup)
    os.rename(staged, final)
    shutil.rmtree(backup, ignore_errors=True)


_RENAME_EXCHANGE = 2  # linux/fs.h


def exchange_paths(a: Path, b: Path) -> bool:
    """Swap two paths in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False where the OS or the
    filesystem cannot, and the caller falls back to two renames. Python's os module has no binding for it."""
    if not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    if not hasattr(libc, "renameat2"):
        return False
    at_fdcwd = -100
    result = libc.renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE)
    if result == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(error, f"cannot swap {a} and {b}: {os.strerror(error)}")


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def recover_interrupted_swap(final: Path) -> None:
    """Clean up after a killed writer of ``final``: if it died between the two renames of a swap (``final``
    missing, its old copy hidden beside it), put the old copy back; remove staged copies of dead processes."""
    leftovers = []
    for kind in ("old", "partial"):
        for path in final.parent.glob(f".{final.name}.{kind}-*"):
            pid = path.name.rsplit(f".{kind}-", 1)[1].split("-")[0]
            if pid.isdigit() and not pid_alive(int(pid)):
                leftovers.append((kind, path))
    for kind, path in sorted(leftovers, key=lambda item: item[0] != "old"):
        if kind == "old" and not final.exists():
            os.rename(path, final)
        else:
            shutil.rmtree(path, ignore_errors=True)


@contextmanager
def dataset_lock(root: Path) -> Iterator[None]:
    """Hold the one-writer lock of the dataset at ``root`` for the whole block; a second writer stops at once with
    the holder's PID. The lock file sits beside the root (``.<name>.lock``; the root itself is swapped out when a
    write completes) and is removed on release. It also checks first that the root's folder takes new files, as
    every write here builds the new dataset beside the old one.

    Written on ``fcntl.flock`` directly: ``filelock`` truncates the file on every try, erasing the holder's PID."""
    root = Path(root).absolute()
    path = root.parent / f".{root.name}.lock"
    while True:
        try:
            root.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as error:
            raise CommandError(
                f"--dataset.root={root}: cannot write in its folder {root.parent} ({error.strerror}); the dataset "
                "is written beside itself and swapped in, so that folder must be writable (or copy the dataset to "
                "one that is)"
            ) from error
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise CommandError(
                f"--dataset.root={root} is being written by another process (PID {holder}); wait for it to finish "
                f"or stop it (lock file {path})"
            ) from None
        try:  # the holder before us may have removed the file while we waited on its old inode: lock the new one
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.unlink(path)  # while still held, so that no other process can lock this inode and then see it gone
        os.close(fd)


@contextmanager
def no_image_embedding_without_images() -> Iterator[None]:
    """LeRobot's writer (``save_episode``) runs ``embed_images``, a row-by-row ``datasets`` map, on every episode even
    where no column holds an image (videos are not columns): half the time of recording CartPole's episodes, whose
    rows it leaves as they are. Within this block that map is skipped where no feature needs it; the parquet rows
    written are the same (tests/test_collect.py)."""
    from datasets.features.features import require_storage_embed
    from lerobot.datasets import dataset_writer

    embed_images = dataset_writer.embed_images

    def embed_only_images(dataset):
        needed = any(require_storage_embed(feature) for feature in dataset.features.values())
        return embed_images(dataset) if needed else dataset

    dataset_writer.embed_images = embed_only_images
    try:
        yield
    finally:
        dataset_writer.embed_images = embed_images
