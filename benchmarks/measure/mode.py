"""What a continuous checkpoint's mode does on the expert's own states, engine by engine (LunarLander): how often
its main engine agrees with the expert's on or off (a ≥ 0), and how often each fires its side engine (|a| > 0.5).
On the frames where the expert stands still on the ground (both legs down, |vx|, |vy| < 0.1, a successor in the
episode), it also gives the expert's main-engine command there, the IDM's label of that transition (its mode:
what the policy learns) and the policy mode's, each as a mean and the share above 0 (the engine fires at ≥ 50%
power for any a > 0, and a lander that fires never comes to rest).

    python benchmarks/measure/mode.py --data outputs/bench-r5/data/lunarlander-aa5adda054-expert-actions \
        --checkpoints outputs/bench-r5/runs/continuous/lunarlander/{bco,iupe}-s{0,2}/checkpoints/last/pretrained_model
    python benchmarks/measure/mode.py --weights selected latest --data … --checkpoints …

``--data`` is an expert dataset with its true actions; every checkpoint reads its states through its own
observation keys (its policy model with one observation per window, the mode of its Gaussian). ``--weights
latest`` reads the run's last trained weights from the training state saved beside the checkpoint instead of the
selected model's.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

STILL = 0.1  # |vx|, |vy| below this count as standing still (the env's goal check)


def engines(checkpoint: Path, data: Path, weights: str = "selected") -> dict[str, float]:
    # Imported here, after the flags are checked: a wrong flag is refused before torch and LeRobot load.
    import torch
    from lerobot.datasets import LeRobotDataset

    from lerobot_iupe.data.readers import ExpertFrames
    from lerobot_iupe.policy.modeling_iupe import IUPEPolicy
    from lerobot_iupe.policy.training_state import TRAINING_STATE_FILE

    policy = IUPEPolicy.from_pretrained(checkpoint)
    if weights == "latest":
        state = torch.load(checkpoint / TRAINING_STATE_FILE, map_location="cpu", weights_only=True)
        policy.load_state_dict(state["latest_weights"])
    policy.eval()
    dataset = LeRobotDataset(f"local/{data.name}", root=data, video_backend="pyav")
    expert = ExpertFrames(dataset, policy.config.observation_keys, True, torch.device("cpu"))
    rows = np.arange(len(expert.states))
    with torch.no_grad():
        output = policy.pm_history_output(expert.windows(rows, policy.config.obs_window))
        mode = policy.pm_head.as_float_action(policy.pm_head.mode(output)).numpy()
        idm = policy.idm_head.as_float_action(
            policy.idm_head.mode(policy.idm_window_output(expert.windows(rows, policy.config.idm_window)))
        ).numpy()
    true = expert.actions.numpy()
    state = expert.states.numpy()  # gymnasium's 8-D state: x, y, vx, vy, angle, angular velocity, two leg contacts
    at_rest = (state[:, 6] > 0) & (state[:, 7] > 0) & (np.abs(state[:, 2]) < STILL) & (np.abs(state[:, 3]) < STILL)
    at_rest &= rows != expert.last_row
    return {
        "main_on_off_agree": float(np.mean((true[:, 0] >= 0) == (mode[:, 0] >= 0))),
        "side_fires_expert": float(np.mean(np.abs(true[:, 1]) > 0.5)),
        "side_fires_mode": float(np.mean(np.abs(mode[:, 1]) > 0.5)),
        "rest_frames": int(at_rest.sum()),
        "rest_main_expert": float(true[at_rest, 0].mean()),
        "rest_main_idm_label": float(idm[at_rest, 0].mean()),
        "rest_idm_label_fires": float(np.mean(idm[at_rest, 0] > 0)),
        "rest_main_mode": float(mode[at_rest, 0].mean()),
        "rest_mode_fires": float(np.mean(mode[at_rest, 0] > 0)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="an expert dataset with its true actions")
    parser.add_argument("--checkpoints", type=Path, nargs="+", required=True, help="pretrained_model folders")
    parser.add_argument(
        "--weights", nargs="+", choices=["selected", "latest"], default=["selected"],
        help="the selected model (model.safetensors) and/or the run's last trained weights (its training state)",
    )  # fmt: skip
    args = parser.parse_args()
    if not (args.data / "meta" / "info.json").is_file():
        parser.error(f"--data={args.data} is not a LeRobot dataset (no meta/info.json)")
    from lerobot_iupe.policy.training_state import TRAINING_STATE_FILE

    for checkpoint in args.checkpoints:
        if "latest" in args.weights and not (checkpoint / TRAINING_STATE_FILE).is_file():
            parser.error(f"--weights=latest: {checkpoint} holds no {TRAINING_STATE_FILE} (a lerobot-train checkpoint)")
        for weights in args.weights:
            result = engines(checkpoint, args.data, weights)
            print(f"{checkpoint} ({weights}): " + ", ".join(f"{k} {v:.3f}" for k, v in result.items()))


if __name__ == "__main__":
    main()
