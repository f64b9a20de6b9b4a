"""What a continuous checkpoint's mode does on the expert's own states, engine by engine (LunarLander): how often
its main engine agrees with the expert's on or off (a ≥ 0), and how often each fires its side engine (|a| > 0.5).

    python scripts/measure_mode.py --data outputs/bench-r5/data/lunarlander-aa5adda054-expert-actions \
        --checkpoints outputs/bench-r5/runs/continuous/lunarlander/{bco,iupe}-s{0,2}/checkpoints/last/pretrained_model

``--data`` is an expert dataset with its true actions; every checkpoint reads its states through its own
observation keys (its policy model with one observation per window, the mode of its Gaussian).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.readers import ExpertFrames
from lerobot_iupe.policy.modeling_iupe import IUPEPolicy


def engines(checkpoint: Path, data: Path) -> dict[str, float]:
    policy = IUPEPolicy.from_pretrained(checkpoint)
    policy.eval()
    dataset = LeRobotDataset(f"local/{data.name}", root=data, video_backend="pyav")
    expert = ExpertFrames(dataset, policy.config.observation_keys, True, torch.device("cpu"))
    rows = np.arange(len(expert.states))
    with torch.no_grad():
        output = policy.pm_history_output(expert.windows(rows, policy.config.obs_window))
        mode = policy.pm_head.as_float_action(policy.pm_head.mode(output)).numpy()
    true = expert.actions.numpy()
    return {
        "main_on_off_agree": float(np.mean((true[:, 0] >= 0) == (mode[:, 0] >= 0))),
        "side_fires_expert": float(np.mean(np.abs(true[:, 1]) > 0.5)),
        "side_fires_mode": float(np.mean(np.abs(mode[:, 1]) > 0.5)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="an expert dataset with its true actions")
    parser.add_argument("--checkpoints", type=Path, nargs="+", required=True, help="pretrained_model folders")
    args = parser.parse_args()
    if not (args.data / "meta" / "info.json").is_file():
        parser.error(f"--data={args.data} is not a LeRobot dataset (no meta/info.json)")
    for checkpoint in args.checkpoints:
        result = engines(checkpoint, args.data)
        print(f"{checkpoint}: " + ", ".join(f"{k} {v:.3f}" for k, v in result.items()))


if __name__ == "__main__":
    main()
