"""Worker processes that end with the process that started them. A worker blocked on a queue does not notice its
parent's death by itself: a relabel killed with SIGKILL (or by the kernel for memory) left its decoding workers
re-parented to init, ~550 MB each, asleep until someone killed them."""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
import time

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
POLL_SECONDS = 1.0


def exit_with_parent(parent_pid: int) -> None:
    """Called first thing in a worker process started by ``parent_pid``: the worker is killed when that process dies
    (Linux: the kernel's parent-death signal; elsewhere a daemon thread that watches the parent's pid). Exits at once
    if the parent has already died. Nothing a worker holds is written anywhere, so a killed worker loses nothing."""
    if sys.platform.startswith("linux"):
        # Written by hand because neither the standard library nor torch exposes prctl; one call, no polling.
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
            _watch_parent(parent_pid)
    else:
        _watch_parent(parent_pid)
    if os.getppid() != parent_pid:  # died before the signal was armed
        os._exit(1)


def _watch_parent(parent_pid: int) -> None:
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(POLL_SECONDS)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
