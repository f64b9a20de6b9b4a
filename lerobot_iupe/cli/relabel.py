"""lerobot-iupe-relabel: give a state-only dataset (state or video) an `action` feature, labelled by the inverse
dynamics model of a trained IUPE checkpoint, in place and safely.

Examples:
    lerobot-iupe-relabel --policy.path=outputs/iupe/checkpoints/last/pretrained_model \
        --dataset.repo_id=local/cartpole-expert --dataset.root=data/cartpole-expert
    lerobot-iupe-relabel --policy.path=... --dataset.repo_id=me/maze5-videos --dry_run=true
    lerobot-iupe-relabel --policy.path=... --dataset.repo_id=me/maze5-videos --dataset.push_to_hub=true
The checkpoint may come from a full IUPE run or from `lerobot-train --policy.type=iupe --policy.supervised=true` on
any labelled dataset of the same robot; the dataset may be any LeRobot v3 dataset with the observations the IDM
reads (checked: keys, shapes, fps, action names). Several processes split the episodes and write the same bytes:
    torchrun --nproc_per_node=2 $(which lerobot-iupe-relabel) --policy.path=... --dataset.repo_id=...
A dataset missing locally is pulled from the hub first. The last frame of each episode (it has no successor)
repeats the label of the frame before it. The dataset is rewritten beside itself and swapped in when complete;
an existing `action` feature is only replaced with --overwrite=true.
"""

from lerobot.configs import parser

from lerobot_iupe.cli import run_cli
from lerobot_iupe.relabel import RelabelConfig, relabel
from lerobot_iupe.relabel.config import RENAMED_FLAGS


@parser.wrap()
def relabel_main(cfg: RelabelConfig) -> None:
    report = relabel(cfg)
    if not report.first_process:
        return
    print(report.summary())
    if report.written:
        print(f"relabelled dataset at {report.root}")
    if cfg.dataset.push_to_hub:
        from lerobot_iupe.hub import push_dataset

        url = push_dataset(report.root, cfg.dataset.repo_id, private=cfg.dataset.private)
        print(f"pushed to {url}")


def main() -> None:
    run_cli(relabel_main, renamed=RENAMED_FLAGS)


if __name__ == "__main__":
    main()
