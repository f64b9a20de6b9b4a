"""What a chunk of labels does when played: the held-out episodes of `downstream.py`'s datasets replayed open loop in
their env, once with the true actions and once with the IDM's labels, from the same reset (episode i of the expert
dataset was recorded from ``reset(seed=i)``).

    python benchmarks/measure/replay_labels.py --work /tmp/w/dl-peg --envs metaworld_peg_insert_side

For each it reports the task's success (as `lerobot-eval` counts it: the env's ``is_success`` at some step), how far
the replayed hand drifts from the recorded one (mean and final distance, metres), the labels' error per dimension and
its lag-1 autocorrelation (an error that persists over a chunk is, to a chunked policy, the expert's intent), and how
far one chunk of 10 labels moves the hand from where the recording went when it starts from the recorded state (the
true actions replayed up to its first frame): what a chunked policy that learnt the labels exactly would do between
two observations. Beside them, the true actions with an independent error of the same size. Writes
replay_labels.{json,md} into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.envs.configs import env_config_from_settings

sys.path.insert(0, str(Path(__file__).parent))
from downstream import ENV_SETTINGS, ENVS  # noqa: E402
from steps import command_line, parse_with_folders  # noqa: E402

HAND = slice(0, 3)  # Meta-World's observation.state starts with the hand's x, y, z
CHUNK = 10  # the chunk the downstream ACT plays open loop


def episodes_of(root: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Each episode's (states, actions) of the dataset at ``root``."""
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    index = column_array(dataset.hf_dataset, "episode_index")
    states, actions = column_array(dataset.hf_dataset, "observation.state"), action_array(dataset)
    return {int(e): (states[index == e], actions[index == e]) for e in np.unique(index)}


def replay(env, seed: int, actions: np.ndarray) -> tuple[bool, np.ndarray]:
    """``actions`` played open loop from ``reset(seed=seed)``: success and the hand's positions s_1 … s_T."""
    # by hand, not envs.rollout.run_episodes: a replay stops when its actions run out, mid-episode for a chunk
    observation, _ = env.reset(seed=seed)
    success, hands = False, []
    for action in actions:
        observation, _, terminated, truncated, info = env.step(action)
        success |= bool(info.get("is_success", False))
        hands.append(np.asarray(observation["agent_pos"], dtype=np.float64)[HAND])
        if terminated or truncated:
            break
    return success, np.array(hands)


def chunk_drift(env, seed: int, true: np.ndarray, played: np.ndarray, states: np.ndarray) -> list[float]:
    """For each chunk start t (every ``CHUNK`` frames): the true actions replayed to frame t, then
    ``played[t:t+CHUNK]``; the distance of the hand at t + CHUNK from the recorded one."""
    drifts = []
    for start in range(0, len(true) - CHUNK + 1, CHUNK):
        _, hands = replay(env, seed, np.concatenate([true[:start], played[start : start + CHUNK]]))
        if len(hands) == start + CHUNK:  # the episode did not end inside the chunk
            drifts.append(float(np.linalg.norm(hands[-1] - states[start + CHUNK, HAND])))
    return drifts


def autocorrelation(error: np.ndarray) -> float:
    error = error - error.mean()
    return float((error[1:] * error[:-1]).sum() / max((error**2).sum(), 1e-12))


def measure(env_name: str, work: Path, variant: str) -> dict:
    truth = episodes_of(work / f"{env_name}-true")
    labels = episodes_of(work / f"{env_name}-idm-{variant}")
    held_out = [e for e in sorted(truth) if e >= ENVS[env_name][0] // 5]
    env = env_config_from_settings(ENV_SETTINGS[env_name]).make()
    low, high = env.action_space.low, env.action_space.high
    result = {"env": env_name, "labels": variant, "episodes": len(held_out)}
    errors = [labels[e][1][:-1] - truth[e][1][:-1] for e in held_out]  # the last frame has no step
    rms = np.sqrt(np.mean(np.concatenate(errors) ** 2, axis=0))
    rng = np.random.default_rng(0)
    # the control: the true actions with an error as large as the labels' but independent from frame to frame
    noisy = {e: (None, np.clip(truth[e][1] + rng.normal(0, rms, truth[e][1].shape), low, high)) for e in held_out}
    for arm, source in (("true", truth), ("idm", labels), ("true_plus_white_noise", noisy)):
        successes, mean_drift, final_drift, chunk = [], [], [], []
        for episode in held_out:
            states, actions = truth[episode][0], source[episode][1][:-1]
            success, hands = replay(env, episode, actions)
            drift = np.linalg.norm(hands - states[1 : 1 + len(hands), HAND], axis=1)
            successes.append(success)
            mean_drift.append(float(drift.mean()))
            final_drift.append(float(drift[-1]))
            if arm != "true":
                chunk += chunk_drift(env, episode, truth[episode][1][:-1], actions, states)
        result[arm] = {
            "success": float(np.mean(successes)),
            "hand_drift_mean_m": float(np.mean(mean_drift)),
            "hand_drift_final_m": float(np.median(final_drift)),
            "chunk_drift_mm": 1000 * float(np.mean(chunk)) if chunk else 0.0,
        }
    env.close()
    result["error_rms"] = [float(v) for v in rms]
    motion = [np.linalg.norm(truth[e][0][CHUNK:, HAND] - truth[e][0][:-CHUNK, HAND], axis=1) for e in held_out]
    result["expert_chunk_motion_mm"] = 1000 * float(np.mean(np.concatenate(motion)))
    result["error_lag1"] = [
        float(np.mean([autocorrelation(e[:, d]) for e in errors])) for d in range(errors[0].shape[1])
    ]
    return result


def render(rows: list[dict], command: str) -> str:
    lines = [
        "# Labels replayed open loop: do they reach the recorded states and the task?",
        "",
        f"`{command}` — the held-out episodes of `downstream.py`'s datasets (not the IDM's training episodes), each "
        "replayed from the reset it was recorded from, all its actions played open loop. Success as `lerobot-eval` "
        "counts it. The control adds to the true actions an independent normal error per frame as large as the "
        "labels' (their rms per dimension, clipped to the action range, seed 0). Hand drift: the distance between "
        "the replayed and the recorded hand (mean over the episode, median over episodes of its final value; 0 for "
        "the true actions, which replay exactly). One chunk's drift: from the recorded state at every 10th frame "
        "(the true actions replayed to it), 10 labels played, the hand's distance from the recorded one (mean over "
        "chunks), beside how far the expert's hand moves in 10 frames. The labels' error rms and lag-1 "
        "autocorrelation per action dimension (mean over episodes).",
        "",
        "| env | labels | episodes | success: true actions / labels / true + white noise | hand drift, labels "
        "(mean / final, m) | hand drift, true + white noise | one chunk's drift, mm: labels / true + white noise "
        "| the expert's hand per chunk, mm | error rms per dimension | error lag-1 autocorrelation |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        t, lab, noise = r["true"], r["idm"], r["true_plus_white_noise"]
        lines.append(
            f"| {r['env']} | {r['labels']} | {r['episodes']} "
            f"| {t['success']:.2f} / {lab['success']:.2f} / {noise['success']:.2f} "
            f"| {lab['hand_drift_mean_m']:.4f} / {lab['hand_drift_final_m']:.4f} "
            f"| {noise['hand_drift_mean_m']:.4f} / {noise['hand_drift_final_m']:.4f} "
            f"| {lab['chunk_drift_mm']:.1f} / {noise['chunk_drift_mm']:.1f} | {r['expert_chunk_motion_mm']:.1f} "
            f"| {', '.join(f'{v:.3f}' for v in r['error_rms'])} | {', '.join(f'{v:.2f}' for v in r['error_lag1'])} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["metaworld_push", "metaworld_pick_place",
                                                     "metaworld_peg_insert_side"])  # fmt: skip
    parser.add_argument("--labels", default="k4", help="the relabelled dataset's variant (<env>-idm-<variant>)")
    args = parse_with_folders(parser, "outputs/replay")
    work, out = Path(args.work), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [measure(env, work, args.labels) for env in args.envs]
    for row in rows:
        print(json.dumps(row), flush=True)
    (out / "replay_labels.json").write_text(json.dumps(rows, indent=1) + "\n")
    (out / "replay_labels.md").write_text(render(rows, command_line()))


if __name__ == "__main__":
    main()
