"""lerobot-iupe-references: expert and uniform-random mean ± std return over seeded episodes, per env.

Example:
    lerobot-iupe-references --episodes=100 --envs=cartpole,acrobot,mountaincar,maze3,maze5,maze10
These are the references of the performance metric P = (R - R_random) / (R_expert - R_random).
"""

import argparse

from lerobot_iupe.envs import AcrobotEnvConfig, CartPoleEnvConfig, MazeEnvConfig, MountainCarEnvConfig
from lerobot_iupe.experts import reference_returns

ENVS = {
    "cartpole": CartPoleEnvConfig,
    "acrobot": AcrobotEnvConfig,
    "mountaincar": MountainCarEnvConfig,
    "maze3": lambda: MazeEnvConfig(size=3),
    "maze5": lambda: MazeEnvConfig(size=5),
    "maze10": lambda: MazeEnvConfig(size=10),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=100, help="episodes per agent and env (default 100)")
    parser.add_argument("--seed", type=int, default=100_000, help="first episode seed (default 100000)")
    parser.add_argument("--envs", default=",".join(ENVS), help=f"comma-separated subset of {','.join(ENVS)}")
    args = parser.parse_args()
    names = [name.strip() for name in args.envs.split(",") if name.strip()]
    unknown = [name for name in names if name not in ENVS]
    if unknown or args.episodes <= 0:
        parser.error(f"--envs: unknown {unknown}; choose from {list(ENVS)}" if unknown else "--episodes must be > 0")
    print(f"| env | expert | random |  ({args.episodes} episodes, seeds {args.seed}…)")
    print("|---|---|---|")
    for name in names:
        cfg = ENVS[name]()
        expert = reference_returns(cfg, "expert", args.episodes, args.seed)
        random = reference_returns(cfg, "random", args.episodes, args.seed)
        print(f"| {name} | {expert.mean():.2f} ± {expert.std():.2f} | {random.mean():.2f} ± {random.std():.2f} |")


if __name__ == "__main__":
    main()
