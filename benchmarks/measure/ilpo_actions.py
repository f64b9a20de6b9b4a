"""Where an ILPO run's actions go wrong, measured on the expert's own transitions (its labelled copy, which ILPO
never saw): how often the latent policy's choice argmax π(z|s) is the latent action z* that explains the expert's
step, how often the remapping maps (s, z*) to the expert's action, and how often the composed policy
(argmax π, then the remapping) acts as the expert did.

    python benchmarks/measure/ilpo_actions.py --work outputs/benchmark --env acrobot --methods ilpo ilpo_norm
"""

import argparse
from pathlib import Path

import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.benchmark import CHECKPOINT
from lerobot_iupe.data.readers import load_transitions
from lerobot_iupe.ilpo import ILPOPolicy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="outputs/benchmark", help="a benchmark's --work folder")
    parser.add_argument("--env", default="acrobot", help="a Table 1 env the benchmark trained ILPO on")
    parser.add_argument("--methods", nargs="+", default=["ilpo"], help="ilpo and/or ilpo_norm")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="training seeds")
    args = parser.parse_args()
    work = Path(args.work)
    (root,) = sorted((work / "data").glob(f"{args.env}-*-expert-actions"))
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    print("| method | seed | argmax π = z* | remapping(s, z*) = a | policy = a |\n|---|---|---|---|---|")
    for method in args.methods:
        for seed in args.seeds:
            run = work / "runs" / "table1" / args.env / f"{method}-s{seed}" / CHECKPOINT
            policy = ILPOPolicy.from_pretrained(run).eval()
            moves = load_transitions(dataset, policy.config.observation_keys, "pyav", policy.config.layout)
            states, next_states = torch.as_tensor(moves.states), torch.as_tensor(moves.next_states)
            actions = torch.as_tensor(moves.actions)
            with torch.no_grad():
                frames, next_frames = policy.flat(states), policy.flat(next_states)
                chosen = policy.lpn(frames)[0].argmax(-1)
                explaining = policy.explaining_latents(frames, next_frames)
                remapped = policy.arn.head.mode(policy.arn(frames, explaining))
                acted = policy.arn.head.mode(policy.arn(frames, chosen))
            rates = [(chosen == explaining), (remapped == actions), (acted == actions)]
            print(f"| {method} | {seed} | " + " | ".join(f"{float(r.float().mean()):.3f}" for r in rates) + " |")


if __name__ == "__main__":
    main()
