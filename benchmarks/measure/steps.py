"""The steps the measurements repeat, so that each script reads as its experiment alone: run an installed command,
train into a folder once with lerobot-train, relabel as a dry run, name the command that made a page, and write a
page with its rows. Training and evaluation themselves are the package's (``lerobot_iupe.benchmark``)."""

from __future__ import annotations

import itertools
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

from lerobot_iupe.benchmark.runner import BIN, CHECKPOINT

# What every measurement's lerobot-train shares: on the CPU, no loader workers, nothing pushed or logged remotely.
TRAIN_FLAGS = ("--num_workers=0", "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false")

__all__ = [
    "BIN", "CHECKPOINT", "TRAIN_FLAGS", "command_line", "dry_run", "extend_once", "parse_with_folders", "run",
    "train_once", "write_page",
]  # fmt: skip


def run(*args: str, threads: int | None = None, log: Path | None = None) -> str:
    """Run an installed console script (``threads``: its OMP_NUM_THREADS), its command line printed; its standard
    output (``log`` gets both streams). A failure prints the command's tail and stops the measurement."""
    print("$", " ".join(args), flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)} if threads else None
    result = subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True, env=env)
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(result.stdout + result.stderr)
    if result.returncode:
        print(result.stdout[-3000:], result.stderr[-3000:])
        raise SystemExit(f"{args[0]} failed ({result.returncode})")
    return result.stdout


def train_once(dataset: Path, out: Path, *flags: str, steps: int, threads: int | None = 1) -> Path:
    """``lerobot-train`` on the dataset at ``dataset`` into ``out`` for ``steps`` steps (one checkpoint, at the end)
    with ``flags`` and those of ``TRAIN_FLAGS`` that ``flags`` does not set; its log beside ``out``. Skipped when
    ``out`` already holds the checkpoint; a run left half-done is removed first. Returns the checkpoint."""
    given = {flag.split("=", 1)[0] for flag in flags}
    shared = [flag for flag in TRAIN_FLAGS if flag.split("=", 1)[0] not in given]
    if not (out / CHECKPOINT).exists():
        shutil.rmtree(out, ignore_errors=True)
        run(
            "lerobot-train", *flags, *shared, f"--dataset.repo_id=local/{dataset.name}",
            f"--dataset.root={dataset}", f"--output_dir={out}", f"--steps={steps}", f"--save_freq={steps}",
            threads=threads, log=out.parent / f"{out.name}.log",
        )  # fmt: skip
    return out / CHECKPOINT


def extend_once(shorter: Path, out: Path, steps: int, threads: int | None = 1) -> Path:
    """The finished run ``shorter`` copied to ``out`` and trained on to ``steps`` with ``lerobot-train --resume=true``
    (LeRobot restores the optimizer, the schedule and the data order), so that a longer budget reuses a shorter one's
    steps; skipped when ``out`` already holds the checkpoint. Returns the checkpoint."""
    if not (out / CHECKPOINT).exists():
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(shorter, out, symlinks=True)
        run(
            "lerobot-train", f"--config_path={out / CHECKPOINT / 'train_config.json'}", "--resume=true",
            f"--output_dir={out}", f"--steps={steps}", f"--save_freq={steps}",
            threads=threads, log=out.parent / f"{out.name}.log",
        )  # fmt: skip
    return out / CHECKPOINT


def dry_run(checkpoint: Path, root: Path, **options):
    """``lerobot-iupe-relabel --dry_run=true`` of ``checkpoint`` on the dataset at ``root``, in this process: its
    report (labels scored against the dataset's own actions where it has them)."""
    from lerobot_iupe.relabel.config import CheckpointRef, RelabelConfig, RelabelDataset
    from lerobot_iupe.relabel.run import relabel

    dataset = RelabelDataset(repo_id=f"local/{root.name}", root=str(root), video_backend="pyav")
    return relabel(RelabelConfig(policy=CheckpointRef(path=str(checkpoint)), dataset=dataset, dry_run=True, **options))


def resolution_of(checkpoint: Path) -> str:
    """The working resolution a checkpoint reads its cameras at (``config.json``'s ``resize_shape``), as ``H×W``."""
    shape = json.loads((checkpoint / "config.json").read_text()).get("resize_shape")
    return "×".join(str(side) for side in shape) if shape else "as stored"


def printed_r2(output: str) -> dict[str, float]:
    """The IDM's R² per action dimension from a relabel's printed report: its one line ("R² per dimension:
    a=0.99, …") or its table beside the references (the IDM's column)."""
    line = re.search(r"R² per dimension: (.*)", output)
    if line:
        return {name: float(value) for name, value in re.findall(r"([\w.]+)=([-\d.]+)", line.group(1))}
    table = output[output.index("R² per dimension") :].splitlines()[1:]
    rows = (re.match(r"\s+([\w.]+)\s+(-?[\d.]+)\s", row) for row in table)
    return {row.group(1): float(row.group(2)) for row in itertools.takewhile(bool, rows)}


def parse_with_folders(parser, work: str, out: str = "benchmarks"):
    """``parser``'s arguments with ``--work`` (runs and data, created if missing) and ``--out`` (where the page is
    written) added, parsed."""
    parser.add_argument("--work", default=work, help="where runs and data are kept (reused when found)")
    parser.add_argument("--out", default=out, help="where the page and its JSON are written")
    args = parser.parse_args()
    Path(args.work).mkdir(parents=True, exist_ok=True)
    return args


def command_line() -> str:
    """How this measurement was started (``python benchmarks/measure/<script> <args>``): what its page cites."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(Path(__file__).resolve().parents[2])
    except ValueError:
        pass
    return " ".join(["python", str(script), *sys.argv[1:]])


def read_page(out: Path, stem: str) -> tuple[list[dict], list[str]]:
    """The rows and commands of ``<stem>.json`` in ``out`` (``write_page``), empty where there is none yet, so that a
    measurement can add to its page; a page of one command keeps it as a string, of several as a list."""
    path = out / f"{stem}.json"
    if not path.exists():
        return [], []
    page = json.loads(path.read_text())
    return page["rows"], page["commands"] if "commands" in page else [page["command"]]


def write_page(
    out: Path, stem: str, command: str | list[str], rows: list[dict], title: str, intro: str, table: list[str]
) -> None:
    """A measurement's ``<stem>.json`` (its command, or its commands where its rows come from several, and its rows)
    and ``<stem>.md`` (title, command(s), what it measured, a table) in ``out``; the page is printed too."""
    key = "command" if isinstance(command, str) else "commands"
    (out / f"{stem}.json").write_text(json.dumps({key: command, "rows": rows}, indent=1) + "\n")
    shown = command if isinstance(command, str) else "`, `".join(command)
    lines = [f"# {title}", "", f"`{shown}`: {intro}", "", *table]
    (out / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
