"""The simplest loop beside the Meta-World table: a plain torch MLP (2×256, ReLU, MSE on standardised inputs, Adam
1e-3, 100 epochs of 256) trained on the same 10 expert demonstrations' true actions that the benchmark's BC reads
(its ``expert-actions`` dataset, observation.state and observation.environment_state), played by its mean and scored
on the same 50 episodes (seeds 500000…) through the same env: benchmarks/metaworld/plain.md and plain.json.

    python benchmarks/measure/metaworld_plain.py --work outputs/metaworld --tasks push pick-place --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.benchmark import EVAL_SEED, METAWORLD
from lerobot_iupe.data.readers import column_array
from lerobot_iupe.envs.configs import env_config_from_settings

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, write_page  # noqa: E402

KEYS = ("observation.state", "observation.environment_state")


def expert_data(work: Path, env: str) -> tuple[np.ndarray, np.ndarray]:
    """Observations and true actions of the benchmark's expert-actions dataset of ``env`` (collected by its run)."""
    preset = METAWORLD[env]
    root = work / "data" / f"{env}-{preset.data_key(False)}-expert-actions"
    if not root.exists():
        raise SystemExit(f"--work: {root} is missing: run lerobot-iupe-benchmark --tables metaworld --envs {env} first")
    data = LeRobotDataset(f"local/{root.name}", root=root).hf_dataset
    observations = np.concatenate([column_array(data, key) for key in KEYS], axis=1)
    return observations.astype(np.float32), column_array(data, "action").astype(np.float32)


def fit(observations: np.ndarray, actions: np.ndarray, seed: int, epochs: int = 100):
    torch.manual_seed(seed)
    mean, std = observations.mean(0), observations.std(0) + 1e-6
    net = torch.nn.Sequential(
        torch.nn.Linear(observations.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
        torch.nn.Linear(256, actions.shape[1]),
    )  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), 1e-3)
    x, y = torch.as_tensor((observations - mean) / std), torch.as_tensor(actions)
    for _ in range(epochs):
        for batch in torch.randperm(len(x)).split(256):
            loss = ((net(x[batch]) - y[batch]) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

    def act(observation: dict) -> np.ndarray:
        flat = np.concatenate([observation["agent_pos"], observation["environment_state"]])
        with torch.no_grad():
            action = net(torch.as_tensor((flat - mean) / std, dtype=torch.float32)[None])[0].numpy()
        return np.clip(action, -1.0, 1.0)

    return act


def success_rate(env: str, act, episodes: int) -> float:
    environment = env_config_from_settings(METAWORLD[env].env).make()
    successes = []
    for i in range(episodes):
        observation, _ = environment.reset(seed=EVAL_SEED + i)
        success = False
        while True:
            observation, _, terminated, truncated, info = environment.step(act(observation))
            success |= bool(info.get("is_success"))
            if terminated or truncated:
                break
        successes.append(success)
    environment.close()
    return float(np.mean(successes))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("outputs/metaworld"), help="the benchmark's --work")
    parser.add_argument("--tasks", nargs="+", default=[e.removeprefix("mw-") for e in METAWORLD])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/metaworld"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for task in args.tasks:
        env = f"mw-{task}"
        if env not in METAWORLD:
            parser.error(f"--tasks: {task!r} is not one of {[e.removeprefix('mw-') for e in METAWORLD]}")
        observations, actions = expert_data(args.work, env)
        for seed in args.seeds:
            rate = success_rate(env, fit(observations, actions, seed), args.episodes)
            rows.append({"task": task, "seed": seed, "success_rate": rate, "episodes": args.episodes})
            print(rows[-1], flush=True)
    lines = ["| task | plain MLP, true actions: success % (per seed) | mean |", "|---|---|---|"]
    for task in args.tasks:
        rates = [100 * r["success_rate"] for r in rows if r["task"] == task]
        lines.append(f"| {task} | {', '.join(f'{r:.0f}' for r in rates)} | {np.mean(rates):.1f} |")
    intro = (
        "a plain 2×256 MLP on the 10 expert demonstrations' true actions (the data BC reads), played by its mean on "
        f"{args.episodes} episodes from seed {EVAL_SEED}, the table's episodes."
    )
    args.out.mkdir(parents=True, exist_ok=True)
    write_page(args.out, "plain", command_line(), rows, "Meta-World: a plain MLP beside the table", intro, lines)


if __name__ == "__main__":
    main()
