"""The CPU runtime a policy trains, acts and labels with: the torch thread count (shared by both policies'
``select_action``) and the C allocator's habit of handing freed memory back."""

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager

import torch

# Allocations up to this size come from the heap, and up to RETAINED_BYTES of freed heap stay with the process.
HEAP_ALLOCATION_BYTES = 256 << 20
RETAINED_BYTES = 1 << 30
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)


@contextmanager
def acting_threads(threads: int) -> Iterator[None]:
    """Run the block on ``threads`` torch threads (0: as they are) and give the caller back its own count."""
    before = torch.get_num_threads()
    if threads and threads != before:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


def keep_freed_memory() -> bool:
    """Keep freed memory in this process (and the processes it forks) for the next allocation of the same size, instead
    of glibc's default, which unmaps large freed blocks (its threshold moves, up to 32 MB) and trims the heap's top
    once over twice that: each IDM batch would otherwise page-fault its tensors in afresh, which cost a camera IDM
    25% of its time labelling (2.6 against 2.0 ms a window of batch 32 at 96×128); ``lerobot-train``'s steps (batch
    8) showed no change beyond noise. What a process holds at its peak stays resident (+10 MB on a 1.06 GB relabel).
    Set by hand because the allocator's settings are not torch's; no-op (False) where the C library has no
    ``mallopt`` (not glibc)."""
    try:  # the symbols already loaded into this process (libc's among them): no library search
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError, TypeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, HEAP_ALLOCATION_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, RETAINED_BYTES))


def use_cpu_runtime(threads: int) -> None:
    """Training's runtime: ``keep_freed_memory`` and ``threads`` torch threads (0: as they are)."""
    keep_freed_memory()
    if threads:
        torch.set_num_threads(threads)
