"""Why LeRobot's ACT trains worse on LunarLander's labels than on its true actions: ACT trained as
`downstream.py --act replan` trains it, on the expert dataset with actions made from the labels or the true
actions to differ from them in one known way each, 3 seeds per control, each evaluated as `downstream.py`
evaluates (`eval_policy_all` on seeds 500000…).

    python benchmarks/measure/act_controls.py --work /tmp/w/dl-lun

Reads `<work>/lunarlander-true` and the labels `<work>/lunarlander-idm-k1-pull1`, both made by
`downstream.py --envs lunarlander --arms --idm_context 1 --pull_to_observation 1`. Controls:

- `labels_true_engines`: the labels, with each frame where a label switches an engine other than the true action
  does (main on/off; side engine off, left or right) given its true action: the labels' errors of size alone.
- `labels_canonical_engines`: what a user without the true actions could do where the actuator's dead zones are
  known: a classifier (a 2×256 MLP on [s_t, s_{t+1} − s_t], cross-entropy) trained on the IDM's 10 labelled
  episodes tells whether each engine fires; a label the classifier says is off is set to its dead zone's centre
  (main −0.5, side 0: the same effect as any value there), one it says is on is kept at least `MARGIN` beyond the
  threshold.
- `true_drift`: the true actions plus a drifting noise (AR(1), 0.8 a frame, about the labels' own lag-1
  autocorrelation) as large as the labels' error per dimension, clipped to the action range: errors of the labels'
  size and persistence, in no relation to the engines.

Writes benchmarks/act_controls.json and .md.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.benchmark.evaluation import evaluate_checkpoint
from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.envs.configs import env_config_from_settings
from lerobot_iupe.relabel.writing import copy_dataset, write_labels

sys.path.insert(0, str(Path(__file__).parent))
from chunk_labels import drifting_noise  # noqa: E402
from downstream import ENV_SETTINGS, POLICY_SETTINGS, lunar_effect, train  # noqa: E402
from steps import command_line, read_page, write_page  # noqa: E402

ACT, STEPS, EVAL_EPISODES = "replan", 3000, 50
CONTROLS = ("labels_true_engines", "labels_canonical_engines", "true_drift")
LABELLED_EPISODES, MARGIN = 10, 0.05


def engine_class(actions: np.ndarray) -> np.ndarray:
    """Per frame: main engine on (1) or off (0); side engine left (-1), off (0) or right (1)."""
    effect = lunar_effect(actions)
    return np.stack([effect[:, 0] > 0, np.sign(effect[:, 1])], axis=1).astype(np.int8)


def labels_with_true_engines(labels: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``labels`` where they switch each engine as ``true`` does, ``true`` where they do not (per dimension)."""
    return np.where(engine_class(labels) == engine_class(true), labels, true).astype(np.float32)


def observation_pairs(true_set: LeRobotDataset) -> np.ndarray:
    """[s_t, s_{t+1} − s_t] of every frame (an episode's last frame: difference 0), standardised."""
    table = true_set.hf_dataset
    keys = ("observation.state", "observation.environment_state")
    state = np.concatenate([column_array(table, key) for key in keys], 1).astype(np.float32)
    episode = column_array(table, "episode_index")
    following = np.append(episode[:-1] == episode[1:], False)
    after = np.where(following[:, None], np.roll(state, -1, axis=0), state)
    pairs = np.concatenate([state, after - state], 1)
    return (pairs - pairs.mean(0)) / (pairs.std(0) + 1e-6)


def classified_engines(pairs: np.ndarray, true: np.ndarray, train_rows: np.ndarray, seed: int = 0) -> np.ndarray:
    """Each frame's ``engine_class`` as a 2×256 MLP predicts it from ``pairs``, trained by cross-entropy on
    ``train_rows`` (4,000 steps of 256, Adam 1e-3)."""
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(pairs.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256), torch.nn.ReLU(),
        torch.nn.Linear(256, 5),
    )  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    x = torch.as_tensor(pairs[train_rows])
    classes = torch.as_tensor(engine_class(true[train_rows]).astype(np.int64) + np.array([0, 1]))
    for _ in range(4000):
        rows = torch.randint(len(x), (256,))
        logits = net(x[rows])
        loss = torch.nn.functional.cross_entropy(logits[:, :2], classes[rows, 0])
        loss = loss + torch.nn.functional.cross_entropy(logits[:, 2:], classes[rows, 1])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        logits = net(torch.as_tensor(pairs))
    return np.stack([logits[:, :2].argmax(1).numpy(), logits[:, 2:].argmax(1).numpy() - 1], 1).astype(np.int8)


def canonical_labels(labels: np.ndarray, engines: np.ndarray) -> np.ndarray:
    """``labels`` with each engine as ``engines`` says: off at its dead zone's centre, on at least ``MARGIN``
    beyond its threshold (main on above 0, side engine on beyond ±0.5)."""
    main = np.where(engines[:, 0] == 1, np.maximum(labels[:, 0], MARGIN), -0.5)
    side = np.where(engines[:, 1] != 0, engines[:, 1] * np.maximum(np.abs(labels[:, 1]), 0.5 + MARGIN), 0.0)
    return np.stack([main, side], 1).astype(np.float32)


def true_with_drift(true: np.ndarray, labels: np.ndarray, episode: np.ndarray, seed: int = 0) -> np.ndarray:
    scale = np.sqrt(((labels - true) ** 2).mean(0))
    noisy = true + drifting_noise(episode, scale, 0.8, np.random.default_rng(seed))
    return np.clip(noisy, -1.0, 1.0).astype(np.float32)


def control_dataset(work: Path, name: str, true_set: LeRobotDataset, actions: np.ndarray) -> Path:
    root = work / f"lunarlander-control-{name}"
    if not (root / "meta" / "info.json").exists():
        staged = root.with_name(root.name + ".partial")
        shutil.rmtree(staged, ignore_errors=True)
        copy_dataset(true_set.root, staged)
        write_labels(staged, actions, dict(true_set.meta.features["action"]))
        staged.rename(root)
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--controls", nargs="+", default=list(CONTROLS), choices=CONTROLS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    args = parser.parse_args()
    true_root, labels_root = args.work / "lunarlander-true", args.work / "lunarlander-idm-k1-pull1"
    true_set = LeRobotDataset(f"local/{true_root.name}", root=true_root)
    true, episode = action_array(true_set), column_array(true_set.hf_dataset, "episode_index")
    labels = action_array(LeRobotDataset(f"local/{labels_root.name}", root=labels_root))
    actions = {
        "labels_true_engines": lambda: labels_with_true_engines(labels, true),
        "labels_canonical_engines": lambda: canonical_labels(
            labels, classified_engines(observation_pairs(true_set), true, np.flatnonzero(episode < LABELLED_EPISODES))
        ),
        "true_drift": lambda: true_with_drift(true, labels, episode),
    }
    datasets, quality = {}, {}
    for name in args.controls:
        made = actions[name]()
        datasets[name] = control_dataset(args.work, name, true_set, made)
        error = made - true
        quality[name] = {
            "error_rms": np.sqrt((error**2).mean(0)).round(4).tolist(),
            "engine_agreement": (engine_class(made) == engine_class(true)).mean(0).round(4).tolist(),
        }
        print(name, quality[name], flush=True)

    def train_control(job):
        name, seed = job
        start = time.perf_counter()
        checkpoint = train(datasets[name], args.work / f"lunarlander-act-control-{name}-s{seed}-{ACT}-{STEPS}",
                           STEPS, seed, POLICY_SETTINGS["act"][ACT])  # fmt: skip
        return checkpoint, time.perf_counter() - start

    jobs = [(name, seed) for name in args.controls for seed in args.seeds]
    with ThreadPoolExecutor(args.jobs) as pool:
        trained = list(pool.map(train_control, jobs))
    torch.set_num_threads(1)
    env_cfg = env_config_from_settings(ENV_SETTINGS["lunarlander"])
    rows, commands = read_page(args.out, "act_controls")
    for (name, seed), (checkpoint, train_s) in zip(jobs, trained, strict=True):
        start = time.perf_counter()
        result = evaluate_checkpoint(checkpoint, env_cfg, EVAL_EPISODES)
        row = {"control": name, "seed": seed, "act": ACT, "act_steps": STEPS, "episodes": EVAL_EPISODES,
               "success_rate": result["pc_success"] / 100.0, "train_s": round(train_s),
               "eval_s": round(time.perf_counter() - start), **quality[name]}  # fmt: skip
        rows = [r for r in rows if (r["control"], r["seed"]) != (name, seed)] + [row]
        print(json.dumps(row), flush=True)
    write(args.out, rows, list(dict.fromkeys([*commands, command_line()])))  # every command whose rows the page keeps


def write(out: Path, rows: list[dict], commands: list[str]) -> None:
    table = ["| actions | seed | success | engine agreement (main, side) | error rms (main, side) | train s |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for row in sorted(rows, key=lambda r: (r["control"], r["seed"])):
        table.append(
            f"| {row['control']} | {row['seed']} | {row['success_rate']:.2f} | "
            f"{', '.join(f'{x:.3f}' for x in row['engine_agreement'])} | "
            f"{', '.join(f'{x:.3f}' for x in row['error_rms'])} | {row['train_s']} |"
        )
    parts = (__doc__ or "").split("\n\n")
    intro = "\n\n".join([parts[0], *parts[2:-1]])  # what each control is, without the usage line
    write_page(out, "act_controls", commands, rows, "ACT on LunarLander: controls for the labels' gap", intro, table)


if __name__ == "__main__":
    main()
