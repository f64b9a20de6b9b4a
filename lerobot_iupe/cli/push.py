"""lerobot-iupe-push: upload an existing dataset root to the hub, with the package's dataset card.

Example:
    lerobot-iupe-push --dataset.root=data/cartpole-expert --dataset.repo_id=me/cartpole-expert
Pulling back is plain LeRobot: LeRobotDataset("me/cartpole-expert").
"""

from dataclasses import dataclass, field

from lerobot.configs import parser

from lerobot_iupe.cli import run_cli
from lerobot_iupe.data.storage import DatasetTarget, resolve_root
from lerobot_iupe.hub import push_dataset


@dataclass
class PushConfig:
    dataset: DatasetTarget = field(default_factory=DatasetTarget)
    # The license the dataset card declares (a hub license id).
    license: str = "apache-2.0"


@parser.wrap()
def push_main(cfg: PushConfig) -> None:
    root = resolve_root(cfg.dataset.repo_id, cfg.dataset.root)
    repo = push_dataset(root, cfg.dataset.repo_id, private=cfg.dataset.private, license=cfg.license)
    print(f"pushed {root} to {repo}")


def main() -> None:
    run_cli(push_main)


if __name__ == "__main__":
    main()
