"""`make demo`: the main job on an embedded default — local CartPole datasets, CPU, no hub.

Collects a state-only expert dataset and random pre-demonstrations with `lerobot-iupe-collect` into
outputs/demo/data and prints what was recorded.
"""

import shutil
import subprocess
import sys
from pathlib import Path

OUT = Path("outputs/demo")
BIN = Path(sys.executable).parent


def run(*args: str) -> None:
    print("$", " ".join(args), flush=True)
    subprocess.run([str(BIN / args[0]), *args[1:]], check=True)


def main() -> None:
    shutil.rmtree(OUT, ignore_errors=True)
    data = OUT / "data"
    run(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=expert",
        "--episodes=10",
        "--seed=0",
        "--dataset.repo_id=local/cartpole-expert",
        f"--dataset.root={data / 'cartpole-expert'}",
    )
    run(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=random",
        "--episodes=200",
        "--seed=1000",
        "--dataset.repo_id=local/cartpole-random",
        f"--dataset.root={data / 'cartpole-random'}",
    )
    print(f"\ndatasets in {data}: load them with LeRobotDataset(repo_id, root=...)")


if __name__ == "__main__":
    main()
