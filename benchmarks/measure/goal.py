"""How often a checkpoint reaches the goal the IUPE cycle checks (``info["goal_reached"]`` at some step) against the
success LeRobot's evaluation counts (``info["is_success"]``), under both evaluation rules.

    python benchmarks/measure/goal.py --checkpoint outputs/runs/iupe-s0/checkpoints/last/pretrained_model

Plays ``--episodes`` episodes on seeds ``--seed`` … in the env the checkpoint records, by the policy's mode
(``argmax``) and by one draw per step (``sample``), and prints one line per rule.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def measure(checkpoint: Path, episodes: int, seed: int, rule: str) -> dict[str, float]:
    """The IUPE cycle's own rollout (batched, envs made by LeRobot's ``make_env``), by the mode or by draws."""
    # Imported here, after the flags are checked: a wrong flag is refused at once, not after torch and LeRobot load.
    from lerobot_iupe.envs.configs import env_config_from_settings
    from lerobot_iupe.policy.modeling_iupe import IUPEPolicy
    from lerobot_iupe.policy.training import IUPETrainer

    policy = IUPEPolicy.from_pretrained(checkpoint)
    trainer = IUPETrainer(policy, dataset_meta=None, seed=seed)
    trainer.use_env(env_config_from_settings(policy.config.env_settings))
    _, goals, returns, successes = trainer.rollout(episodes, seed, explore=rule == "sample")
    return {"goal_reached": float(goals.mean()), "is_success": float(successes.mean()), "return": float(returns.mean())}


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
