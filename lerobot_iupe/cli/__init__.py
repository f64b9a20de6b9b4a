"""The package's console scripts (``lerobot-iupe-*``): thin wrappers that parse flags and print results."""

from __future__ import annotations

import sys
from collections.abc import Callable

from lerobot_iupe.errors import CommandError


def run_cli(main: Callable[[], object], renamed: dict[str, str] | None = None) -> None:
    """Run a CLI body; turn the package's input errors into one clear line and exit code 2. ``renamed``: old flag
    → its LeRobot name, refused with the new name rather than draccus' bare "unrecognized arguments"."""
    for old, new in (renamed or {}).items():
        if any(arg == old or arg.startswith(f"{old}=") for arg in sys.argv[1:]):
            print(f"error: {old} is now {new} (LeRobot's name for it)", file=sys.stderr)
            sys.exit(2)
    try:
        main()
    except (ValueError, FileExistsError, FileNotFoundError, CommandError) as error:
        print(f"error: {error}", file=sys.stderr)
        sys.exit(2)
