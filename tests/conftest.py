import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("HF_HUB_OFFLINE", "0")

BIN = Path(sys.executable).parent


def run_cli(name: str, *args: str, env: dict | None = None, check: bool = True) -> subprocess.CompletedProcess:
    """Run one of the installed console scripts (lerobot-iupe-*, lerobot-train, lerobot-eval) for real."""
    result = subprocess.run(
        [str(BIN / name), *args], capture_output=True, text=True, env={**os.environ, **(env or {})}, timeout=600
    )
    if check and result.returncode != 0:
        raise AssertionError(f"{name} failed ({result.returncode}):\n{result.stdout[-3000:]}\n{result.stderr[-5000:]}")
    return result


@pytest.fixture(scope="session")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def collect(data_dir: Path, name: str, *args: str) -> Path:
    root = data_dir / name
    if not root.exists():
        run_cli("lerobot-iupe-collect", f"--dataset.repo_id=local/{name}", f"--dataset.root={root}", *args)
    return root


@pytest.fixture(scope="session")
def cartpole_expert(data_dir) -> Path:
    return collect(data_dir, "cartpole-expert", "--env.type=cartpole", "--agent=expert", "--episodes=10")


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
def cartpole_run(cartpole_expert, cartpole_random, tmp_path_factory) -> Path:
    """A normal small IUPE training run on CartPole (200 steps); its output directory."""
    out = tmp_path_factory.mktemp("runs") / "cartpole"
    run_cli(
        "lerobot-train",
        *train_args(
            cartpole_expert,
            cartpole_random,
            out,
            "--steps=200",
            "--batch_size=128",
            "--save_freq=200",
            "--log_freq=50",
            "--policy.cycle_steps=50",
        ),
    )
    return out


@pytest.fixture(scope="session")
def maze_run(maze_expert, maze_random, tmp_path_factory) -> Path:
    """A tiny Maze 3×3 run (4 steps): a real image checkpoint, not a trained one."""
    out = tmp_path_factory.mktemp("runs") / "maze"
    run_cli(
        "lerobot-train",
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
    return out


def evaluate(checkpoint, output, *env_args: str, episodes: int) -> dict:
    run_cli(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        *env_args,
        f"--eval.n_episodes={episodes}",
        f"--eval.batch_size={episodes}",
        "--eval.use_async_envs=false",
        f"--output_dir={output}",
        "--policy.device=cpu",
        "--seed=500000",
    )
    return json.loads((output / "eval_info.json").read_text())["overall"]
