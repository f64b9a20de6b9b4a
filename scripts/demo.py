"""`make demo`: the main job on an embedded default — local CartPole data, CPU, no hub.

1. `lerobot-iupe-collect`: a state-only expert dataset (10 episodes) and random pre-demonstrations.
2. `lerobot-train --policy.type=iupe`: the full IUPE algorithm.
3. `lerobot-eval`: 50 episodes on seeds never used in training.
4. P and AER against the expert and random references measured from the two datasets.
The checkpoint stays at outputs/demo/train/checkpoints/last/pretrained_model.
"""

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from lerobot_iupe.algorithm import performance
from lerobot_iupe.dataset_utils import read_iupe_meta

OUT = Path("outputs/demo")
BIN = Path(sys.executable).parent


def run(*args: str) -> None:
    print("\n$", " ".join(args), flush=True)
    subprocess.run([str(BIN / args[0]), *args[1:]], check=True)


def main() -> None:
    shutil.rmtree(OUT, ignore_errors=True)
    data = OUT / "data"
    expert, random = data / "cartpole-expert", data / "cartpole-random"
    run(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=expert",
        "--episodes=10",
        "--seed=0",
        "--dataset.repo_id=local/cartpole-expert",
        f"--dataset.root={expert}",
    )
    run(
        "lerobot-iupe-collect",
        "--env.type=cartpole",
        "--agent=random",
        "--episodes=400",
        "--seed=1000",
        "--dataset.repo_id=local/cartpole-random",
        f"--dataset.root={random}",
    )
    start = time.perf_counter()
    run(
        "lerobot-train",
        "--policy.type=iupe",
        "--dataset.repo_id=local/cartpole-expert",
        f"--dataset.root={expert}",
        "--policy.pre_demos_repo_id=local/cartpole-random",
        f"--policy.pre_demos_root={random}",
        f"--output_dir={OUT / 'train'}",
        "--steps=200",
        "--batch_size=128",
        "--policy.cycle_steps=50",
        "--save_freq=200",
        "--log_freq=50",
        "--num_workers=0",
        "--policy.device=cpu",
        "--wandb.enable=false",
    )
    train_seconds = time.perf_counter() - start
    checkpoint = OUT / "train/checkpoints/last/pretrained_model"
    run(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        "--env.type=cartpole",
        "--eval.n_episodes=50",
        "--eval.batch_size=50",
        "--eval.use_async_envs=false",
        "--seed=500000",
        f"--output_dir={OUT / 'eval'}",
        "--policy.device=cpu",
    )
    overall = json.loads((OUT / "eval/eval_info.json").read_text())["overall"]
    expert_return, random_return = read_iupe_meta(expert)["mean_return"], read_iupe_meta(random)["mean_return"]
    aer = overall["avg_sum_reward"]
    p = performance([aer], expert_return, random_return)  # P is linear in R: P of the mean return = mean P
    print("\n| method | env | P | AER | success | train s |")
    print("|---|---|---|---|---|---|")
    print(f"| IUPE | cartpole | {p:.3f} | {aer:.1f} | {overall['pc_success']:.0f}% | {train_seconds:.0f} |")
    print(f"references: expert {expert_return:.1f} (demonstrations), random {random_return:.1f} (pre-demonstrations)")
    print(f"checkpoint: {checkpoint}")


if __name__ == "__main__":
    main()
