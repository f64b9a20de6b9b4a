"""`make demo`: the main job on an embedded default — local CartPole data, CPU, no hub.

1. `lerobot-iupe-collect`: a state-only expert dataset and random pre-demonstrations.
2. `lerobot-train --policy.type=iupe`: the full IUPE algorithm.
3. `lerobot-eval`: episodes on seeds never used in training (mazes: on held-out layouts too).
4. P and AER against the expert and random references measured from the two datasets.

    python scripts/demo.py                      # CartPole, the `make demo` default
    python scripts/demo.py --env mountaincar    # also: acrobot, maze5
The checkpoint stays at outputs/demo/train/checkpoints/last/pretrained_model (outputs/demo-<env> for others).
"""

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from lerobot_iupe.algorithm import performance
from lerobot_iupe.dataset_utils import read_iupe_meta

BIN = Path(sys.executable).parent

# env name -> (env flags, expert collect flags, random collect flags, train flags, eval episodes)
PRESETS = {
    "cartpole": (["--env.type=cartpole"], ["--episodes=10"], ["--episodes=400"], [], 50),
    "mountaincar": (["--env.type=mountaincar"], ["--episodes=10"], ["--episodes=100"], [], 50),
    "acrobot": (["--env.type=acrobot"], ["--episodes=10"], ["--episodes=40"], [], 50),
    "maze5": (
        ["--env.type=maze", "--env.size=5"],
        ["--episodes=100"],
        ["--episodes=400", "--random_start=true", "--env.max_steps=25"],
        ["--steps=600", "--batch_size=64", "--policy.cycle_steps=150", "--policy.rollout_episodes=20"],
        50,
    ),
}
DEFAULT_TRAIN = ["--steps=200", "--batch_size=128", "--policy.cycle_steps=50"]


def run(*args: str) -> None:
    print("\n$", " ".join(args), flush=True)
    subprocess.run([str(BIN / args[0]), *args[1:]], check=True)


def evaluate(checkpoint: Path, env_flags: list[str], episodes: int, output: Path) -> dict:
    run(
        "lerobot-eval",
        f"--policy.path={checkpoint}",
        *env_flags,
        f"--eval.n_episodes={episodes}",
        f"--eval.batch_size={min(episodes, 50)}",
        "--eval.use_async_envs=false",
        "--seed=500000",
        f"--output_dir={output}",
        "--policy.device=cpu",
    )
    return json.loads((output / "eval_info.json").read_text())["overall"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=sorted(PRESETS), default="cartpole")
    args = parser.parse_args()
    env_flags, expert_flags, random_flags, train_flags, eval_episodes = PRESETS[args.env]
    out = Path("outputs/demo" if args.env == "cartpole" else f"outputs/demo-{args.env}")
    shutil.rmtree(out, ignore_errors=True)
    expert, random = out / "data" / f"{args.env}-expert", out / "data" / f"{args.env}-random"
    run(
        "lerobot-iupe-collect",
        *env_flags,
        "--agent=expert",
        *expert_flags,
        "--seed=0",
        f"--dataset.repo_id=local/{expert.name}",
        f"--dataset.root={expert}",
    )
    run(
        "lerobot-iupe-collect",
        *env_flags,
        "--agent=random",
        *random_flags,
        "--seed=1000",
        f"--dataset.repo_id=local/{random.name}",
        f"--dataset.root={random}",
    )
    start = time.perf_counter()
    run(
        "lerobot-train",
        "--policy.type=iupe",
        f"--dataset.repo_id=local/{expert.name}",
        f"--dataset.root={expert}",
        "--dataset.video_backend=pyav",
        f"--policy.pre_demos_repo_id=local/{random.name}",
        f"--policy.pre_demos_root={random}",
        f"--output_dir={out / 'train'}",
        *(train_flags or DEFAULT_TRAIN),
        "--save_freq=100000",
        "--log_freq=50",
        "--num_workers=0",
        "--policy.device=cpu",
        "--wandb.enable=false",
    )
    train_seconds = time.perf_counter() - start
    checkpoint = out / "train/checkpoints/last/pretrained_model"
    expert_return, random_return = read_iupe_meta(expert)["mean_return"], read_iupe_meta(random)["mean_return"]
    if args.env.startswith("maze"):
        # the random reference of a maze is a random walk from the start cell under the normal step cap
        from lerobot_iupe.envs import MazeEnvConfig
        from lerobot_iupe.experts import reference_returns

        random_return = float(reference_returns(MazeEnvConfig(size=int(args.env[4:])), "random", 100).mean())
        settings = [("demo layouts", []), ("held-out layouts", ["--env.layouts=heldout"])]
    else:
        settings = [("", [])]
    print("\n| method | env | eval | P | AER | success | train s |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for name, flags in settings:
        overall = evaluate(checkpoint, env_flags + flags, eval_episodes, out / f"eval{'-'.join(flags)}")
        aer = overall["avg_sum_reward"]
        p = performance([aer], expert_return, random_return)  # P is linear in R: P of the mean return = mean P
        rows.append(
            f"| IUPE | {args.env} | {name} | {p:.3f} | {aer:.3f} | {overall['pc_success']:.0f}% | {train_seconds:.0f} |"
        )
    print("\n".join(rows))
    print(f"references: expert {expert_return:.3f} (demonstrations), random {random_return:.3f}")
    print(f"checkpoint: {checkpoint}")


if __name__ == "__main__":
    main()
