"""lerobot-iupe-collect: record expert or random demonstrations of the package's envs as a LeRobot dataset.

Examples:
    lerobot-iupe-collect --env.type=cartpole --agent=expert --episodes=20 \
        --dataset.repo_id=local/cartpole-expert --dataset.root=data/cartpole-expert --seed=0
    lerobot-iupe-collect --env.type=maze --env.size=5 --agent=random --random_start=true --episodes=200 \
        --dataset.repo_id=local/maze5-random --dataset.root=data/maze5-random --seed=1000
    lerobot-iupe-collect --env.type=so101_pickplace --agent=random --episodes=100 \
        --dataset.repo_id=local/so101-random --dataset.root=data/so101-random --seed=1000
    lerobot-iupe-collect --env.type=metaworld_state --env.task=push-v3 --agent=expert --episodes=10 \
        --dataset.repo_id=local/push-expert --dataset.root=data/push-expert
Env types: cartpole, acrobot, mountaincar, maze (discrete actions, int64 ids), lunarlander, so101_pickplace,
metaworld_state (continuous actions, float32 with the env's action names; Meta-World tasks by --env.task).
Agents: expert, random, and play (goal-agnostic play: so101_pickplace, metaworld_state).
Expert datasets carry no `action` column unless --keep_actions=true; random datasets always carry it.
"""

from lerobot.configs import parser

from lerobot_iupe.cli import run_cli
from lerobot_iupe.collect import RENAMED_FLAGS, CollectConfig, collect


@parser.wrap()
def collect_main(cfg: CollectConfig) -> None:
    root, meta = collect(cfg)
    print(
        f"wrote {meta['episodes']} {cfg.agent} episodes of {cfg.env.type} to {root} in {meta['seconds']:.1f}s: "
        f"mean return {meta['mean_return']:.2f} ± {meta['std_return']:.2f}, success {meta['success_rate']:.0%}"
    )
    if cfg.dataset.push_to_hub:
        from lerobot_iupe.hub import push_dataset

        url = push_dataset(root, cfg.dataset.repo_id, private=cfg.dataset.private)
        print(f"pushed to {url}")


def main() -> None:
    run_cli(collect_main, renamed=RENAMED_FLAGS)


if __name__ == "__main__":
    main()
