"""The package's console scripts (``lerobot-iupe-*``): thin wrappers that parse flags and print results."""

from __future__ import annotations

import sys
from collections.abc import Callable

from lerobot_iupe.errors import CommandError


def run_cli(main: Callable[[], object]) -> None:
    """Run a CLI body; turn the package's input errors into one clear line and exit code 2."""
    try:
        main()
    except (ValueError, FileExistsError, FileNotFoundError, CommandError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
