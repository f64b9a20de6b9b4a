"""How often a checkpoint reaches the goal the IUPE cycle checks (``info["goal_reached"]`` at some step) against the
success LeRobot's evaluation counts (``info["is_success"]``), under both evaluation rules.

    python scripts/measure_goal.py --checkpoint outputs/runs/iupe-s0/checkpoints/last/pretrained_model

Plays ``--episodes`` episodes on seeds ``--seed`` … in the env the checkpoint records, by the policy's mode
(``argmax``) and by one draw per step (``sample``), and prints one line per rule.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from lerobot_iupe.envs.configs import env_config_from_settings, env_observation, env_observation_keys
from lerobot_iupe.envs.rollout import run_episodes
from lerobot_iupe.policy.modeling_iupe import IUPEPolicy


def measure(checkpoint: Path, episodes: int, seed: int, rule: str) -> dict[str, float]:
    policy = IUPEPolicy.from_pretrained(checkpoint)
    policy.config.eval_mode = rule
    policy.eval()
    env_cfg = env_config_from_settings(policy.config.env_settings)
    keys = env_observation_keys(env_cfg)  # env key -> the policy's key
    torch.manual_seed(seed)
    played = []
    for episode_seed in range(seed, seed + episodes):  # one env at a time: select_action keeps one history
        env = env_cfg.make()
        policy.reset()

        def act(observations: list[dict], active: list[int]) -> list:
            batch = {key: torch.as_tensor(env_observation(observations[0], k))[None] for k, key in keys.items()}
            with torch.no_grad():
                return [policy.select_action(batch)[0].numpy()]

        played += run_episodes([env], act, [episode_seed])
        env.close()
    return {
        "goal_reached": float(np.mean([e.goal_reached for e in played])),
        "is_success": float(np.mean([e.success for e in played])),
        "return": float(np.mean([e.total_reward for e in played])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, required=True, help="a pretrained_model folder")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=700_000, help="first episode seed (unseen in training)")
    args = parser.parse_args()
    if not (args.checkpoint / "config.json").is_file():
        parser.error(f"--checkpoint={args.checkpoint} holds no config.json; pass a pretrained_model folder")
    for rule in ("argmax", "sample"):
        result = measure(args.checkpoint, args.episodes, args.seed, rule)
        print(
            f"{rule}: goal reached {result['goal_reached']:.3f}, is_success {result['is_success']:.3f}, "
            f"mean return {result['return']:.1f} over {args.episodes} episodes from seed {args.seed}"
        )


if __name__ == "__main__":
    main()
