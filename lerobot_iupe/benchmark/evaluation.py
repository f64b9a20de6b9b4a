"""Evaluation of the benchmark's runs: a checkpoint exactly as ``lerobot-eval`` evaluates it, a built-in agent on
the same seeds and layouts, and what a training run recorded about itself."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import torch
from lerobot.configs import PreTrainedConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.envs.configs import EnvConfig
from lerobot.policies import make_policy, make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.utils.random_utils import set_seed

from lerobot_iupe.experts import agent_episodes
from lerobot_iupe.policy.training import CYCLES_FILE

EVAL_SEED = 500_000  # evaluation seeds/layouts 500000…: never used by data (0…, 1000…) or rollouts (≥ 1e6)


def load_checkpoint(
    checkpoint: Path, env_cfg: EnvConfig | None = None, ds_meta=None, eval_mode: str | None = None
) -> tuple[PreTrainedConfig, torch.nn.Module, object, object]:
    """A saved policy on the CPU as ``lerobot-eval`` loads it: its config, the policy in eval mode and its
    pre/post-processors; the features come from ``env_cfg`` or ``ds_meta``, as ``make_policy`` takes them."""
    policy_cfg = PreTrainedConfig.from_pretrained(checkpoint)
    policy_cfg.pretrained_path = checkpoint
    policy_cfg.device = "cpu"
    if eval_mode is not None:
        policy_cfg.eval_mode = eval_mode
    policy = make_policy(cfg=policy_cfg, env_cfg=env_cfg, ds_meta=ds_meta).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=policy_cfg,
        pretrained_path=str(checkpoint),
        preprocessor_overrides={"device_processor": {"device": "cpu"}},
    )
    return policy_cfg, policy, preprocessor, postprocessor


@torch.no_grad()
def evaluate_checkpoint(
    checkpoint: Path, env_cfg: EnvConfig, episodes: int, eval_mode: str = "argmax", seed: int = EVAL_SEED
) -> dict:
    """What lerobot-eval does (make_env, make_policy, LeRobot's processors, eval_policy_all), minus videos;
    ``eval_mode`` is ``--policy.eval_mode``."""
    set_seed(seed)
    envs = make_env(env_cfg, n_envs=min(episodes, 50), use_async_envs=False)
    policy_cfg, policy, preprocessor, postprocessor = load_checkpoint(checkpoint, env_cfg=env_cfg, eval_mode=eval_mode)
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=policy_cfg)
    info = eval_policy_all(
        envs=envs, policy=policy, env_preprocessor=env_pre, env_postprocessor=env_post, preprocessor=preprocessor,
        postprocessor=postprocessor, n_episodes=episodes, start_seed=seed,
    )  # fmt: skip
    close_envs(envs)
    return info["overall"]


def evaluate_agent(agent: str, env_cfg: EnvConfig, episodes: int) -> dict:
    """A built-in agent on the evaluation seeds (the same envs, seeds and layouts as ``evaluate_checkpoint``).
    Not through eval_policy_all: the maze expert reads the simulator's state, which a LeRobot policy cannot."""
    returns, successes = agent_episodes(env_cfg, agent, episodes, seed=EVAL_SEED)
    return {"avg_sum_reward": float(returns.mean()), "pc_success": 100.0 * float(successes.mean())}


DATA_S = re.compile(r"data_s:([\d.]+)")


def read_training_run(checkpoint: Path, output: str, steps: int) -> tuple[list[dict], dict]:
    """The run's cycle records (``iupe_cycles.jsonl`` beside the checkpoint; ILPO: its selection points) and its time
    breakdown."""
    path, ilpo = checkpoint / CYCLES_FILE, checkpoint / "ilpo_remapping.json"
    cycles = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
    if ilpo.exists():  # ILPO's selection points stand for cycles
        cycles = json.loads(ilpo.read_text())["selection"]
    data_avg = [float(x) for x in DATA_S.findall(output)]  # LeRobot's own per-step data-loading average
    timing = {
        "rollouts_s": cycles[-1].get("rollouts_s", 0.0) if cycles else 0.0,  # none in a supervised run
        "idm_s": cycles[-1].get("idm_s", 0.0) if cycles else 0.0,
        "selection_s": cycles[-1].get("selection_s", 0.0) if cycles else 0.0,
        "data_loading_s": float(np.mean(data_avg)) * steps if data_avg else 0.0,
    }
    return cycles, timing
