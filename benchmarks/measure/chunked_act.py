"""LeRobot's ACT trained by `lerobot-train` on datasets that differ only in their actions (true actions, an IDM's
labels, labels pulled toward the observation), played as LeRobot users play it, evaluated by LeRobot's evaluation
loop on seeds the data never used. Runs several trainings at once (for a machine with many cores and a GPU).

    python benchmarks/measure/chunked_act.py --datasets true=outputs/dl48/lunarlander-true \\
        idm=outputs/dl48/lunarlander-idm-k1 pull1=outputs/dl48/lunarlander-idm-k1-pull1 \\
        --act replan chunk10 --seeds 0 1 2 --device cuda --jobs 5 --loader_workers 2 --out results.jsonl

Each finished run appends one JSON line to --out (labels, act, seed, steps, success_rate, avg_sum_reward, train_s), so
a run cut short keeps what finished. The ACT flags are those of `benchmarks/measure/downstream.py`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from downstream import ACT_FLAGS, ACT_SETTINGS, CHECKPOINT, ENV_SETTINGS  # noqa: E402

STEPS = {"replan": 3000, "chunk10": 1500, "fit_step": 3000}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--datasets", nargs="+", required=True, help="name=root of each dataset (same frames)")
    parser.add_argument("--env", default="lunarlander", choices=list(ENV_SETTINGS))
    parser.add_argument("--act", nargs="+", default=["replan", "chunk10"], choices=list(ACT_SETTINGS))
    parser.add_argument("--steps", type=int, default=None, help="training steps (default: per ACT setting)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--jobs", type=int, default=2, help="trainings at a time")
    parser.add_argument("--loader_workers", type=int, default=0, help="lerobot-train's --num_workers per training")
    parser.add_argument("--eval_episodes", type=int, default=50)
    parser.add_argument("--work", default="outputs/chunked-act")
    parser.add_argument("--out", default="outputs/chunked-act/results.jsonl")
    args = parser.parse_args()
    datasets = dict(item.split("=", 1) for item in args.datasets)
    work, out = Path(args.work), Path(args.out)
    work.mkdir(parents=True, exist_ok=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()
    # Seed by seed, so that what a cut-short run leaves is whole seeds of every dataset.
    runs = [(act, seed, name) for act in args.act for seed in args.seeds for name in datasets]

    def one(run: tuple[str, int, str]) -> None:
        act, seed, name = run
        steps = args.steps or STEPS.get(act, 1500)
        root = Path(datasets[name])
        output = work / f"{name}-{act}-{steps}-s{seed}"
        start = time.perf_counter()
        if not (output / CHECKPOINT).exists():
            log = open(work / f"{output.name}.log", "w")
            subprocess.run(
                ["lerobot-train", *ACT_FLAGS, *ACT_SETTINGS[act], f"--num_workers={args.loader_workers}",
                 f"--policy.device={args.device}", "--env_eval_freq=0", "--wandb.enable=false", "--log_freq=500",
                 f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", f"--output_dir={output}",
                 f"--steps={steps}", f"--save_freq={steps}", f"--seed={seed}"],
                check=True, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "OMP_NUM_THREADS": "1"},
            )  # fmt: skip
        train_s = time.perf_counter() - start
        evaluation = subprocess.run(
            [sys.executable, "-c", EVALUATE, str(output / CHECKPOINT), json.dumps(ENV_SETTINGS[args.env]),
             str(args.eval_episodes)],
            check=True, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"},
        )  # fmt: skip
        result = json.loads(evaluation.stdout.strip().splitlines()[-1])
        row = {"env": args.env, "labels": name, "act": act, "seed": seed, "steps": steps, "device": args.device,
               "success_rate": result["pc_success"] / 100.0, "avg_sum_reward": result["avg_sum_reward"],
               "episodes": args.eval_episodes, "train_s": train_s}  # fmt: skip
        with lock, out.open("a") as file:
            file.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)

    with ThreadPoolExecutor(args.jobs) as pool:
        for future in [pool.submit(one, run) for run in runs]:
            future.result()


# In a process of its own: LeRobot's evaluation, one thread.
EVALUATE = """
import json, sys, torch
torch.set_num_threads(1)
from lerobot_iupe.benchmark.evaluation import evaluate_checkpoint
from lerobot_iupe.envs.configs import env_config_from_settings
result = evaluate_checkpoint(sys.argv[1], env_config_from_settings(json.loads(sys.argv[2])), int(sys.argv[3]))
print(json.dumps({"pc_success": result["pc_success"], "avg_sum_reward": result["avg_sum_reward"]}))
"""

if __name__ == "__main__":
    main()
