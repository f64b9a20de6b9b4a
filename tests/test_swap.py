"""Write-beside-then-swap under a real SIGKILL at every step of the swap: the root always holds a whole
dataset (the old or the new one), and the next writer on the root cleans up what the dead one left."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from lerobot_iupe.data.storage import exchange_paths, recover_interrupted_swap

WRITER = """
import os, shutil, signal, sys
from pathlib import Path
from lerobot_iupe.data import storage as dataset_utils

point, root = sys.argv[1], Path(sys.argv[2])
die = lambda *_: os.kill(os.getpid(), signal.SIGKILL)
real_exchange, real_rename, real_rmtree = dataset_utils.exchange_paths, os.rename, shutil.rmtree
if point == "before_exchange":
    dataset_utils.exchange_paths = die
elif point == "after_exchange":
    dataset_utils.exchange_paths = lambda a, b: (real_exchange(a, b), die())
elif point == "during_cleanup":  # the old copy half deleted
    dataset_utils.shutil.rmtree = lambda path, **kw: (next(Path(path).rglob("*.txt")).unlink(), die())
else:  # the two-rename fallback, killed after its first rename or before its cleanup
    dataset_utils.exchange_paths = lambda a, b: False
    if point == "between_renames":
        dataset_utils.os.rename = lambda a, b: (real_rename(a, b), die())
with dataset_utils.staged_directory(root, overwrite=True) as staged:
    (staged / "data").mkdir(parents=True)
    for i in range(3):
        (staged / "data" / f"part-{i}.txt").write_text(f"new {i}")
print("finished")
"""


def tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): p.read_text() for p in sorted(root.rglob("*")) if p.is_file()}


def hidden_siblings(root: Path) -> list[Path]:
    return sorted(root.parent.glob(f".{root.name}.*"))


OLD = {f"data/part-{i}.txt": f"old {i}" for i in range(3)}
NEW = {f"data/part-{i}.txt": f"new {i}" for i in range(3)}


@pytest.mark.parametrize(
    ("point", "at_root_after_kill", "at_root_after_recovery"),
    [
        ("before_exchange", OLD, OLD),
        ("after_exchange", NEW, NEW),
        ("during_cleanup", NEW, NEW),
        ("between_renames", None, OLD),  # fallback only: the root is missing until the next writer
    ],
)
def test_a_kill_at_any_step_of_the_swap_leaves_a_whole_dataset(
    tmp_path, point, at_root_after_kill, at_root_after_recovery
):
    root = tmp_path / "dataset"
    (root / "data").mkdir(parents=True)
    for name, text in OLD.items():
        (root / name).write_text(text)
    result = subprocess.run([sys.executable, "-c", WRITER, point, str(root)], capture_output=True, text=True)
    assert result.returncode == -9, result.stderr[-2000:]
    assert "finished" not in result.stdout
    assert (tree(root) if root.exists() else None) == at_root_after_kill
    assert hidden_siblings(root)  # the dead writer left something behind …
    recover_interrupted_swap(root)  # … which the next writer on this root puts back or removes
    assert tree(root) == at_root_after_recovery
    assert hidden_siblings(root) == []


def test_exchange_swaps_two_directories_atomically(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "f").write_text("a")
    (b / "f").write_text("b")
    if not exchange_paths(a, b):
        pytest.skip("this OS or filesystem has no atomic exchange; staged_directory uses two renames")
    assert (a / "f").read_text() == "b" and (b / "f").read_text() == "a"
    assert os.path.isdir(a) and os.path.isdir(b)
