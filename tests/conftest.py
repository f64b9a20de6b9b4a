import atexit
import contextlib
import io
import json
import logging
import os
import runpy
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path

# One intra-op thread per process, set before torch loads and inherited by every command the tests start: two
# xdist workers on two cores, each with two threads, made a CartPole evaluation 27x slower (0.9 s vs 24.8 s).
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402
import torch  # noqa: E402
from filelock import FileLock  # noqa: E402

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("HF_HUB_OFFLINE", "0")
# The frame cache of this test session (data.frame_cache), not the user's; removed when the session that made it
# exits (xdist's workers and the commands the tests start inherit it).
if "LEROBOT_IUPE_CACHE" not in os.environ:
    os.environ["LEROBOT_IUPE_CACHE"] = tempfile.mkdtemp(prefix="lerobot-iupe-frames-")
    atexit.register(shutil.rmtree, os.environ["LEROBOT_IUPE_CACHE"], ignore_errors=True)

BIN = Path(sys.executable).parent


def run_cli(name: str, *args: str, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    """Run one of the installed console scripts (lerobot-iupe-*, lerobot-train, lerobot-eval) for real."""
    result = subprocess.run(
        [str(BIN / name), *args], capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=600
    )
    if check and result.returncode != 0:
        raise AssertionError(f"{name} failed ({result.returncode}):\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}")
    return result


def run_in_process(name: str, *args: str, check: bool = False) -> subprocess.CompletedProcess:
    """An installed command (lerobot-iupe-*, lerobot-train, lerobot-eval) run in this process: its console-script
    function with these arguments, its exit code and output. A new process would spend ~5 s importing torch and
    LeRobot; the commands run as processes where the process is what a test checks (README's workflows, a second
    writer, kill -9, the hub's environment, the benchmark's jobs)."""
    (script,) = [e for e in entry_points(group="console_scripts") if e.name == name]
    return _captured(script.load(), [name, *args], check)


def run_script(path: Path, *args: str, check: bool = False) -> subprocess.CompletedProcess:
    """A repository script (``scripts/…``, ``benchmarks/measure/…``) run in this process as ``__main__`` with these
    arguments, as ``run_in_process`` runs an installed command."""
    return _captured(lambda: runpy.run_path(str(path), run_name="__main__"), [str(path), *args], check)


def _captured(main: Callable[[], object], argv: list[str], check: bool) -> subprocess.CompletedProcess:
    """``main()`` with ``sys.argv = argv``: its exit code and output, and this process's settings as they were."""
    out, err, threads, saved_argv = io.StringIO(), io.StringIO(), torch.get_num_threads(), sys.argv
    # LeRobot's init_logging replaces the root logger's handlers with one bound to this call's captured stderr
    handlers, level = logging.root.handlers[:], logging.root.level
    sys.argv = argv
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
        code = 0
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else int(exit_.code is not None)
    except Exception:  # as Python ends a process on an uncaught exception: the traceback, exit code 1
        traceback.print_exc(file=err)
        code = 1
    finally:
        sys.argv = saved_argv
        torch.set_num_threads(threads)  # lerobot-iupe-relabel sets its own
        logging.root.handlers[:], logging.root.level = handlers, level
    if check and code != 0:
        raise AssertionError(f"{argv[0]} failed ({code}):\n{out.getvalue()[-3000:]}\n{err.getvalue()[-5000:]}")
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


@pytest.fixture(scope="session")
def shared_dir(tmp_path_factory) -> Path:
    """One folder for the whole session, shared by pytest-xdist's workers (``make test`` runs two)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


@pytest.fixture(scope="session")
def data_dir(shared_dir) -> Path:
    path = shared_dir / "data"
    path.mkdir(exist_ok=True)
    return path


def once(path: Path, make: Callable[[], object], done: str = "") -> Path:
    """``make()`` creates ``path`` unless ``path / done`` exists; workers wanting the same ``path`` wait for the
    first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(path.parent / f"{path.name}.fixture-lock"):
        if not (path / done).exists():
            make()
    return path


def collect(data_dir: Path, name: str, *args: str) -> Path:
    """Fixture data recorded by lerobot-iupe-collect in this process (test_collect runs it as a process)."""
    root = data_dir / name

    flags = [f"--dataset.repo_id=local/{name}", f"--dataset.root={root}", *args]
    return once(root, lambda: run_in_process("lerobot-iupe-collect", *flags, check=True))


def train_once(out: Path, *args: str) -> Path:
    """A lerobot-train run into ``out``, shared by every worker; its output directory."""

    def train() -> None:
        shutil.rmtree(out, ignore_errors=True)
        run_in_process("lerobot-train", *args, check=True)

    return once(out, train, CHECKPOINT)


@pytest.fixture(scope="session")
def cartpole_expert(data_dir) -> Path:
    return collect(data_dir, "cartpole-expert", "--env.type=cartpole", "--agent=expert", "--episodes=10")


@pytest.fixture(scope="session")
def cartpole_labelled(data_dir) -> Path:
    """Three CartPole expert episodes with their true actions (supervised training)."""
    return collect(data_dir, "cartpole-expert-labelled", "--env.type=cartpole", "--agent=expert", "--episodes=3",
                   "--keep_actions=true")  # fmt: skip


@pytest.fixture(scope="session")
def maze_random(data_dir) -> Path:
    return collect(
        data_dir,
        "maze3-random",
        "--env.type=maze",
        "--env.size=3",
        "--agent=random",
        "--random_start=true",
        "--episodes=6",
        "--seed=50",
    )


@pytest.fixture(scope="session")
def cartpole_random(data_dir) -> Path:
    return collect(
        data_dir, "cartpole-random", "--env.type=cartpole", "--agent=random", "--episodes=400", "--seed=1000"
    )


@pytest.fixture(scope="session")
def maze_expert(data_dir) -> Path:
    return collect(data_dir, "maze3-expert", "--env.type=maze", "--env.size=3", "--agent=expert", "--episodes=4")


def train_args(expert: Path, pre: Path, output: Path, *extra: str) -> list[str]:
    return [
        "--policy.type=iupe",
        f"--dataset.repo_id=local/{expert.name}",
        f"--dataset.root={expert}",
        "--dataset.video_backend=pyav",
        f"--policy.pre_demos_repo_id=local/{pre.name}",
        f"--policy.pre_demos_root={pre}",
        f"--output_dir={output}",
        "--num_workers=0",
        "--policy.device=cpu",
        "--wandb.enable=false",
        *extra,
    ]


CHECKPOINT = "checkpoints/last/pretrained_model"


@pytest.fixture(scope="session")
def cartpole_run(cartpole_expert, cartpole_random, shared_dir) -> Path:
    """A normal small IUPE training run on CartPole (200 steps); its output directory."""
    out = shared_dir / "runs" / "cartpole"
    return train_once(
        out,
        *train_args(
            cartpole_expert,
            cartpole_random,
            out,
            "--steps=200",
            "--batch_size=128",
            "--save_freq=200",
            "--log_freq=50",
            "--policy.cycle_steps=50",
            "--policy.selection_episodes=8",
        ),
    )


@pytest.fixture(scope="session")
def maze_run(maze_expert, maze_random, shared_dir) -> Path:
    """A tiny Maze 3×3 run (4 steps): a real image checkpoint, not a trained one."""
    out = shared_dir / "runs" / "maze"
    return train_once(
        out,
        *train_args(
            maze_expert,
            maze_random,
            out,
            "--steps=4",
            "--batch_size=8",
            "--save_freq=4",
            "--policy.cycle_steps=2",
            "--policy.rollout_episodes=2",
            "--policy.idm_epochs=1",
        ),
    )


def evaluate(checkpoint, output, *env_args: str, episodes: int) -> dict:
    run_in_process(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        *env_args,
        f"--eval.n_episodes={episodes}",
        f"--eval.batch_size={episodes}",
        "--eval.use_async_envs=false",
        f"--output_dir={output}",
        "--policy.device=cpu",
        "--seed=500000",
        check=True,
    )
    return json.loads((output / "eval_info.json").read_text())["overall"]


def process_gone(pid: int) -> bool:
    """No such process, or one that has exited and waits to be reaped (a zombie holds no memory)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return True
    return state in ("Z", "X")


def still_alive_after(pids: list[int], seconds: float) -> list[int]:
    """Those of ``pids`` still running ``seconds`` from now (killed then, so that a failing test leaves no orphan)."""
    deadline = time.monotonic() + seconds
    while not all(process_gone(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    alive = [pid for pid in pids if not process_gone(pid)]
    for pid in alive:
        os.kill(pid, signal.SIGKILL)
    return alive


# The longest tests (about a minute each on 2 cores) start first, so that the two xdist workers end together
# instead of one running a long test alone at the end.
LONGEST_FIRST = (
    "test_docs.py::test_workflows_1_and_3_run_as_printed",
    "test_docs.py::test_workflow_2_runs_as_printed",
    "test_benchmark.py::test_quick_benchmark_writes_records_tables_and_plots",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: not item.nodeid.endswith(LONGEST_FIRST))
