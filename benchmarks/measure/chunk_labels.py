"""A quick screen of label candidates for chunked policies: the simplest chunked learner (a 2×256 MLP from the
observation to the next 10 actions, L1 loss, batch 64, Adam 1e-3) trained on LunarLander datasets that differ only
in their actions, played open loop (all 10 actions) and re-planned every step (the first), 3 seeds each. Minutes per
candidate on one core, where LeRobot's ACT takes half an hour: it ranks candidates, and ACT confirms the winner
(`benchmarks/measure/downstream.py`).

    python benchmarks/measure/chunk_labels.py --work outputs/dl48

Candidates, all on the frames of `<work>/lunarlander-true` (its first 10 episodes are the IDM's labelled ones):
true actions; the IDM's labels (`lunarlander-idm-k1`, made by `downstream.py --arms`); those labels
pulled toward the observation by 1 std (`lunarlander-idm-k1-pull1`, `--pull_to_observation 1`); the same regression
without a limit (every label replaced by it); a centred moving average over 3 frames; and two controls at the size of
the IDM's error per dimension: the true actions plus independent noise, and plus a drifting noise (AR(1), 0.8 a
frame). Evaluation: the package's LunarLanderEnv on seeds 500000… (safe landings), 30 episodes per run.
Writes benchmarks/chunk_labels.json and .md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.envs.lunar import LunarLanderEnv
from lerobot_iupe.relabel.consistency import observation_regression
from lerobot_iupe.relabel.references import per_dimension_r2

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line  # noqa: E402

CHUNK, STEPS, EVAL_SEED = 10, 3000, 500_000


def load(root: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Episode index, 8-D observation (state, leg contacts) and action of every frame."""
    dataset = LeRobotDataset(f"local/{root.name}", root=root)
    table = dataset.hf_dataset
    states = [column_array(table, key) for key in ("observation.state", "observation.environment_state")]
    return column_array(table, "episode_index"), np.concatenate(states, 1).astype(np.float32), action_array(dataset)


def moving_average(actions: np.ndarray, episode: np.ndarray, width: int) -> np.ndarray:
    out = actions.copy()
    for index in np.unique(episode):
        rows = np.flatnonzero(episode == index)
        padded = np.pad(actions[rows], ((width // 2, width // 2), (0, 0)), mode="edge")
        out[rows] = np.stack([padded[i : i + len(rows)] for i in range(width)]).mean(0)
    return out


def drifting_noise(episode: np.ndarray, scale: np.ndarray, rho: float, rng: np.random.Generator) -> np.ndarray:
    """AR(1) noise restarted at each episode, stationary standard deviation ``scale`` per dimension."""
    noise = np.zeros((len(episode), len(scale)))
    for t in range(len(episode)):
        carried = rho * noise[t - 1] if t and episode[t] == episode[t - 1] else 0.0
        noise[t] = carried + rng.normal(0, 1, len(scale)) * scale * np.sqrt(1 - rho**2)
    return noise


def chunk_targets(actions: np.ndarray, episode: np.ndarray, chunk: int = CHUNK) -> np.ndarray:
    """The next ``chunk`` actions of each frame, the episode's last one repeated past its end (LeRobot pads
    likewise)."""
    index = np.arange(len(actions))[:, None] + np.arange(chunk)[None]
    last = np.array([np.flatnonzero(episode == e)[-1] for e in episode])
    return actions[np.minimum(index, last[:, None])].reshape(len(actions), -1)


def train_chunked(observations: np.ndarray, actions: np.ndarray, episode: np.ndarray, seed: int, chunk: int = CHUNK):
    torch.manual_seed(seed)
    mean, std = observations.mean(0), observations.std(0) + 1e-6
    x = torch.as_tensor((observations - mean) / std)
    y = torch.as_tensor(chunk_targets(actions, episode, chunk), dtype=torch.float32)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 256), torch.nn.ReLU(), torch.nn.Linear(256, 256),
                              torch.nn.ReLU(), torch.nn.Linear(256, y.shape[1]))  # fmt: skip
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(STEPS):
        rows = torch.randint(len(x), (64,), generator=generator)
        loss = (net(x[rows]) - y[rows]).abs().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    def act(observation: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return net(torch.as_tensor((observation - mean) / std)[None]).numpy().reshape(chunk, -1)

    return act


def success_rate(policy, play: int, episodes: int) -> float:
    env, landed = LunarLanderEnv(render_mode=None), 0
    for index in range(episodes):
        observation, _ = env.reset(seed=EVAL_SEED + index)
        queue: list = []
        while True:
            if not queue:
                state = np.concatenate([observation["agent_pos"], observation["environment_state"]])
                queue = list(policy(state)[:play])
            observation, _, terminated, truncated, info = env.step(queue.pop(0))
            if terminated or truncated:
                break
        landed += bool(info["is_success"])
    return landed / episodes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("outputs/dl48"))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--only", nargs="*", default=None, help="candidates to run (default: all)")
    parser.add_argument(
        "--settings", nargs="+", default=["chunk10", "replan"], choices=["chunk10", "replan", "step"],
        help="how the learner plays: chunk10 (10 actions open loop), replan (a chunk every step, its first action), "
        "step (one-action chunks: a per-step policy)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    episode, observations, true = load(args.work / "lunarlander-true")
    labels = load(args.work / "lunarlander-idm-k1")[2]
    error_scale = (labels - true).std(0)
    rng = np.random.default_rng(0)
    candidates = {
        "true actions": true,
        "IDM labels (today)": labels,
        "pulled 1 std (--pull_to_observation=1)": load(args.work / "lunarlander-idm-k1-pull1")[2],
        "replaced by the regression on the observation": np.clip(
            observation_regression(observations, labels, seed=0), -1, 1
        ),
        "moving average, 3 frames": moving_average(labels, episode, 3),
        "control: true + independent noise": np.clip(true + rng.normal(0, 1, true.shape) * error_scale, -1, 1),
        "control: true + drifting noise (AR 0.8)": np.clip(
            true + drifting_noise(episode, error_scale, 0.8, rng), -1, 1
        ),
    }  # fmt: skip
    held_out = episode >= 10
    inner = np.append(episode[:-1] == episode[1:], False)
    rows = []
    for name, actions in candidates.items():
        if args.only and not any(part in name for part in args.only):
            continue
        error = (actions - true)[inner]
        lag1 = [float(np.corrcoef(error[:-1, i], error[1:, i])[0, 1]) for i in range(true.shape[1])]
        steps_true, steps = np.diff(true, axis=0)[inner[:-1]], np.diff(actions, axis=0)[inner[:-1]]
        step_error = np.sqrt(((steps - steps_true) ** 2).mean(0)) / np.sqrt((steps_true**2).mean(0))
        row = {"labels": name, "r2_held_out": per_dimension_r2(actions[held_out & inner], true[held_out & inner]),
               "step_change_error": step_error.tolist(),
               "error_lag1_autocorrelation": lag1, "episodes": args.episodes, "seeds": args.seeds}  # fmt: skip
        for setting in args.settings:
            chunk, play = {"chunk10": (CHUNK, CHUNK), "replan": (CHUNK, 1), "step": (1, 1)}[setting]
            row[setting] = [
                success_rate(train_chunked(observations, actions, episode, seed, chunk), play, args.episodes)
                for seed in args.seeds
            ]
        old = next((r for r in previous(args.out) if r["labels"] == name), {})
        rows.append({**old, **row})
        print(json.dumps(row), flush=True)
    write(args.out, rows, command_line())


def previous(out: Path) -> list[dict]:
    path = out / "chunk_labels.json"
    return json.loads(path.read_text())["rows"] if path.exists() else []


def write(out: Path, rows: list[dict], command: str) -> None:
    path = out / "chunk_labels.json"
    data = json.loads(path.read_text()) if path.exists() else {"commands": []}
    commands = data.get("commands") or [data["command"]]
    commands += [command] if command not in commands else []
    old = data.get("rows", [])
    new = {row["labels"]: row for row in rows}  # in place of the rows they replace, in their order
    rows = [new.pop(row["labels"], row) for row in old] + list(new.values())
    path.write_text(json.dumps({"commands": commands, "rows": rows}, indent=1) + "\n")
    true = next((row for row in rows if row["labels"] == "true actions"), None)
    lines = [
        "# Label candidates for chunked policies: a quick screen",
        "",
        f"{', '.join(f'`{c}`' for c in commands)} (benchmarks/measure/chunk_labels.py says what each candidate is). "
        "The simplest chunked learner, a 2×256 MLP from LunarLander's observation to its next 10 actions (L1, "
        "3,000 steps of 64), trained on the same 50 expert episodes with different actions; success = safe "
        "landings on 30 episodes from seed 500000, per training seed. R² on the 40 episodes the IDM did not train "
        "on. Step-to-step change error: rms(Δlabel − Δtrue) / rms(Δtrue) per dimension, Δ between consecutive "
        "frames. Ratios against the true actions. `step` is the same learner with one-action chunks (a per-step "
        "policy).",
        "",
        "| labels | R² (main, lateral) | step-to-step change error | error lag-1 autocorrelation | chunk10 per seed "
        "| chunk10 mean | ratio | replan per seed | replan mean | ratio | step per seed | step mean | ratio |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lag1 = row["error_lag1_autocorrelation"]
        row["error_lag1_autocorrelation"] = [0.0 if np.isnan(x) else x for x in lag1]  # true actions: no error
        cells = [row["labels"], ", ".join(f"{x:.3f}" for x in row["r2_held_out"]),
                 ", ".join(f"{x:.2f}" for x in row["step_change_error"]),
                 ", ".join(f"{x:.2f}" for x in row["error_lag1_autocorrelation"])]  # fmt: skip
        for setting in ("chunk10", "replan", "step"):
            if setting not in row:
                cells += ["–", "–", "–"]
                continue
            mean = float(np.mean(row[setting]))
            ratio = mean / np.mean(true[setting]) if true and setting in true else float("nan")
            cells += [", ".join(f"{x:.2f}" for x in row[setting]), f"{mean:.3f}", f"{ratio:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Meta-World's labels (push, pick-place, peg-insert-side) replayed through their env, whole episodes "
              "and single chunks from the recorded state: [replay_labels.md](replay_labels.md)."]  # fmt: skip
    (out / "chunk_labels.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
