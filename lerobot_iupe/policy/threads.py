"""The torch thread count a policy acts with, shared by both policies' ``select_action``."""

from collections.abc import Iterator
from contextlib import contextmanager

import torch


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
