"""Do IDM labels train LeRobot's own policies? ACT (or Diffusion Policy, `--policy diffusion`) trained with
`lerobot-train` on (a) an expert dataset with its true actions and (b) the same dataset stripped of its actions and
relabelled by an IDM trained on 20% of its episodes (`--policy.supervised=true`), both evaluated by LeRobot's
evaluation loop; 3 seeds per arm.

    python benchmarks/measure/downstream.py [--envs lunarlander so101_pickplace so101_camera so101_relative]
        [--seeds 0 1 2] [--policy diffusion]

so101_camera is the SO-101 arm seen by its front camera (64 px) with its state: the IDM and ACT read both;
so101_relative also gives the block and goal seen from the end effector (`--env.relative_positions=true`);
metaworld_push (pick_place, peg_insert_side) is Meta-World's push (pick-place, peg-insert-side) observed as state
(`--env.type=metaworld_state`).

A run with a larger `--steps` than an arm's finished run in `--work` resumes that run (`lerobot-train --resume=true`:
LeRobot restores the optimizer, the learning-rate schedule and the data order); its row's `resumed_from_steps` says
from which step, and its training seconds count only the steps after it.

Writes the rows (env, policy, labels, seed, success_rate, …) into benchmarks/relabel.json under "downstream" and
renders benchmarks/relabel.md. Evaluation is `eval_policy_all`, what `lerobot-eval` runs, without its video
rendering, on seeds 500000… never used by the data.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_tools import delete_episodes, remove_feature

from lerobot_iupe.benchmark.evaluation import evaluate_checkpoint, load_checkpoint
from lerobot_iupe.data.readers import action_array, column_array
from lerobot_iupe.envs.configs import env_cli_flags, env_config_from_settings
from lerobot_iupe.policy.algorithm import r_squared

sys.path.insert(0, str(Path(__file__).parent))
from relabel_report import render, update  # noqa: E402
from steps import command_line, extend_once, parse_with_folders, run, train_once  # noqa: E402

CHECKPOINT = "checkpoints/last/pretrained_model"
ENVS = {  # name -> (expert episodes, IDM steps, ACT steps)
    "lunarlander": (50, 2000, 1500),
    "so101_pickplace": (50, 2000, 1500),
    "so101_camera": (50, 2000, 1500),
    "so101_relative": (50, 2000, 1500),
    "metaworld_push": (50, 2000, 1500),
    "metaworld_pick_place": (50, 2000, 1500),
    "metaworld_peg_insert_side": (50, 2000, 1500),
}
# The env settings of each name: SO-101 with its front camera (64 px) and its state, no block or goal positions;
# SO-101 with the block and goal also seen from the end effector.
ENV_SETTINGS = {
    "lunarlander": {"type": "lunarlander"},
    "so101_pickplace": {"type": "so101_pickplace"},
    "so101_camera": {"type": "so101_pickplace", "image_obs": True, "image_size": 64},
    "so101_relative": {"type": "so101_pickplace", "relative_positions": True},
    "metaworld_push": {"type": "metaworld_state", "task": "push-v3"},
    "metaworld_pick_place": {"type": "metaworld_state", "task": "pick-place-v3"},
    "metaworld_peg_insert_side": {"type": "metaworld_state", "task": "peg-insert-side-v3"},
}
# A CPU-sized ACT (LeRobot's defaults are for 480-px cameras): 10-step chunks, 128-wide transformer.
ACT_FLAGS = [
    "--policy.type=act", "--policy.chunk_size=10", "--policy.dim_model=128",
    "--policy.n_heads=4", "--policy.dim_feedforward=512", "--policy.n_encoder_layers=2",
    "--policy.n_decoder_layers=1", "--policy.n_vae_encoder_layers=2", "--policy.optimizer_lr=5e-4",
    "--policy.push_to_hub=false", "--batch_size=64",
]  # fmt: skip
FIT = ["--policy.use_vae=false", "--policy.dropout=0.0", "--policy.optimizer_lr=1e-3"]
# How ACT plays its chunks (LeRobot's own options): all 10 actions open loop; a new chunk every step, its first
# action; a new chunk every step, the chunks' predictions for this step averaged (ACT's temporal ensembling).
ACT_SETTINGS = {
    "chunk10": ["--policy.n_action_steps=10"],
    "replan": ["--policy.n_action_steps=1"],
    # replan without ACT's VAE (LeRobot's other defaults kept): whether the VAE is what label noise upsets
    "replan_novae": ["--policy.n_action_steps=1", "--policy.use_vae=false"],
    "ensemble": ["--policy.n_action_steps=1", "--policy.temporal_ensemble_coeff=0.01"],
    # chunk10 fitted harder: a scripted expert has one action per state, so no VAE, no dropout, learning rate 1e-3
    "fit": ["--policy.n_action_steps=10", *FIT],
    # fit with one-action chunks: ACT as a per-step policy, the next action predicted from each observation
    "fit_step": ["--policy.chunk_size=1", "--policy.n_action_steps=1", *FIT],
}
DEFAULT_ACT = "chunk10"
# LeRobot's Diffusion Policy with its own defaults (2 observations, a 64-action horizon, 32 actions played open loop,
# DDPM with 100 steps, learning rate 1e-4 with its warm-up and cosine schedule) and a CPU-sized U-Net: its default
# widths (512, 1024, 2048) are a 250M-parameter network for GPUs; 128/256/512 took 1.8 s a step of 64 on one of two
# busy cores, 64/128/256 0.8 s (half of it LeRobot loading the 64-action horizons).
DIFFUSION_FLAGS = ["--policy.type=diffusion", "--policy.down_dims=[64,128,256]", "--policy.push_to_hub=false",
                   "--batch_size=64"]  # fmt: skip
# Frames between two of training_fit's checks: Diffusion samples each action with 100 denoising passes.
FIT_EVERY = {"act": 3, "diffusion": 30}
# Each policy's settings, by name: its flags (ACT: how it plays its chunks; Diffusion: LeRobot's defaults only).
POLICY_SETTINGS = {
    "act": {name: ACT_FLAGS + flags for name, flags in ACT_SETTINGS.items()},
    "diffusion": {"lerobot": DIFFUSION_FLAGS},
}
COMMON = ["--env_eval_freq=0", "--log_freq=500"]  # beside steps.TRAIN_FLAGS


def train(dataset: Path, out: Path, steps: int, seed: int, flags: list[str]) -> Path:
    return train_once(dataset, out, *flags, *COMMON, f"--seed={seed}", steps=steps)


def shorter_steps(run: Path | None) -> int | None:
    return None if run is None else int(run.name.rsplit("-", 1)[1])


def shorter_run(work: Path, name: str, steps: int) -> Path | None:
    """The finished run of the arm ``name`` (``<arm>-<act>-<steps>``) with the most steps below ``steps``, which a
    longer budget resumes from (``steps.extend_once``); None where there is none."""
    stem, _, wanted = name.rpartition("-")
    if not wanted.isdigit():
        return None
    finished = [
        run for run in work.glob(f"{stem}-*")
        if run.name.rsplit("-", 1)[1].isdigit() and int(run.name.rsplit("-", 1)[1]) < steps
        and (run / CHECKPOINT).exists()
    ]  # fmt: skip
    return max(finished, key=shorter_steps, default=None)


def training_fit(checkpoint: Path, dataset: Path, every: int = 3) -> list[float]:
    """R² per action dimension of the policy's first action on its own training frames (every ``every``-th), read
    through LeRobot's dataset and processors: whether the policy fits the data it was given, apart from how it
    plays."""
    frames = LeRobotDataset(f"local/{dataset.name}", root=dataset, video_backend="pyav")
    _, policy, preprocessor, postprocessor = load_checkpoint(checkpoint, ds_meta=frames.meta)
    predicted, true = [], []
    for index in range(0, len(frames), every):
        item = frames[index]
        batch = {key: value.unsqueeze(0) for key, value in item.items() if key.startswith("observation.")}
        policy.reset()  # a fresh chunk: its first action is the one predicted for this frame
        with torch.no_grad():
            predicted.append(postprocessor(policy.select_action(preprocessor({**batch, "task": [""]})))[0].numpy())
        true.append(item["action"].numpy())
    predicted, true = np.array(predicted), np.array(true)
    return [r_squared(predicted[:, i], true[:, i]) for i in range(true.shape[1])]


def lunar_effect(actions: np.ndarray) -> np.ndarray:
    """What LunarLanderContinuous does with an action: main-engine power (0 unless a0 > 0, then 0.5–1) and signed
    side-engine power (0 unless |a1| > 0.5, then 0.5–1), as gymnasium's step computes them."""
    main = np.where(actions[:, 0] > 0, (np.clip(actions[:, 0], 0, 1) + 1) / 2, 0.0)
    side = np.where(np.abs(actions[:, 1]) > 0.5, np.sign(actions[:, 1]) * np.clip(np.abs(actions[:, 1]), 0.5, 1), 0)
    return np.stack([main, side], axis=1)


def label_quality(env: str, truth: Path, relabelled: Path, held_out_from: int) -> dict:
    """The labels against the true actions on the episodes the IDM never trained on (``held_out_from``…), frames
    with a successor."""

    def inner_actions(root: Path) -> np.ndarray:
        dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
        episodes = column_array(dataset.hf_dataset, "episode_index")
        keep = np.append(episodes[:-1] == episodes[1:], False) & (episodes >= held_out_from)
        return action_array(dataset)[keep]

    true, labels = inner_actions(truth), inner_actions(relabelled)
    quality = {
        "scored_episodes": "held out (not the IDM's training episodes)",
        "frames": int(len(true)),
        "r2": r_squared(labels, true),
        "r2_per_dim": [r_squared(labels[:, i], true[:, i]) for i in range(true.shape[1])],
    }
    if env == "lunarlander":
        effect_true, effect_labels = lunar_effect(true), lunar_effect(labels)
        quality["effect_r2"] = r_squared(effect_labels, effect_true)
        # whether each engine fires (and which side engine) is what the next state shows most plainly
        quality["engine_agreement"] = [
            float(((effect_labels[:, 0] > 0) == (effect_true[:, 0] > 0)).mean()),
            float((np.sign(effect_labels[:, 1]) == np.sign(effect_true[:, 1])).mean()),
        ]
    return quality


def measure(
    env: str,
    work: Path,
    seeds: list[int],
    episodes_eval: int,
    jobs: int,
    k: int,
    arms: list[str],
    keys: list[str],
    act: str = DEFAULT_ACT,
    act_steps: int | None = None,
    pull: float = 0.0,
    policy: str = "act",
) -> tuple[list[dict], dict]:
    episodes, idm_steps, default_act_steps = ENVS[env]
    act_steps = act_steps or default_act_steps
    truth, labelled = work / f"{env}-true", work / f"{env}-labelled"
    variant = f"k{k}" + "".join(f"-{key.split('.')[-1]}" for key in keys)  # e.g. k1-front: the camera alone
    labels_variant = variant + (f"-pull{pull:g}" if pull else "")  # the IDM's labels moved toward the observation
    stripped, relabelled = work / f"{env}-stripped", work / f"{env}-idm-{labels_variant}"
    env_flags = env_cli_flags(ENV_SETTINGS[env])
    if not truth.exists():
        run(
            "lerobot-iupe-collect", *env_flags, "--agent=expert", f"--episodes={episodes}", "--seed=0",
            "--keep_actions=true", f"--dataset.repo_id=local/{truth.name}", f"--dataset.root={truth}",
        )  # fmt: skip
    source = LeRobotDataset(f"local/{truth.name}", root=truth, video_backend="pyav")
    n_labelled = max(1, episodes // 5)  # 20% of the episodes keep their actions
    if not labelled.exists():
        delete_episodes(source, list(range(n_labelled, episodes)), labelled, f"local/{labelled.name}")
        (labelled / "meta" / "iupe.json").unlink(missing_ok=True)  # LeRobot's own files only
    idm_flags = ["--policy.type=iupe", "--policy.supervised=true", f"--policy.idm_context={k}"]
    idm_flags += [f"--policy.observation_keys=[{','.join(keys)}]"] if keys else []
    idm = train(labelled, work / f"{env}-idm-{variant}-train", idm_steps, 0, idm_flags)
    read = ", ".join(json.loads((idm / "config.json").read_text())["observation_keys"])
    shutil.rmtree(stripped, ignore_errors=True)
    shutil.rmtree(relabelled, ignore_errors=True)
    remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
    shutil.copytree(stripped, relabelled)
    start = time.perf_counter()
    run("lerobot-iupe-relabel", f"--policy.path={idm}", f"--dataset.repo_id=local/{relabelled.name}",
        f"--dataset.root={relabelled}", f"--pull_to_observation={pull}")  # fmt: skip
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    quality = {"env": env, "commit": commit, "idm_context": k, "idm_reads": read, "pull_to_observation": pull,
               "labelled_episodes": n_labelled, "episodes": episodes,
               "idm_steps": idm_steps, "relabel_s": time.perf_counter() - start,
               **label_quality(env, truth, relabelled, held_out_from=n_labelled)}  # fmt: skip
    print(json.dumps(quality), flush=True)
    if not arms:
        return [], quality
    env_cfg = env_config_from_settings(ENV_SETTINGS[env])
    datasets = {"true": truth, "idm": relabelled}
    runs = [(labels, datasets[labels], seed) for labels in arms for seed in seeds]

    resumed_from: dict[str, int | None] = {}

    def train_arm(run) -> tuple[Path, float | None]:
        labels, dataset, seed = run
        start = time.perf_counter()
        arm = "true" if labels == "true" else f"idm-{labels_variant}"
        name = f"{env}-{policy}-{arm}-s{seed}"
        if (policy, act, act_steps) != ("act", DEFAULT_ACT, default_act_steps):
            name += f"-{act}-{act_steps}"
        reused = (work / name / CHECKPOINT).exists()
        shorter = None if reused else shorter_run(work, name, act_steps)
        if shorter is not None:
            print(f"{name}: resumed from {shorter.name}", flush=True)
            checkpoint = extend_once(shorter, work / name, act_steps)
        else:
            checkpoint = train(dataset, work / name, act_steps, seed, POLICY_SETTINGS[policy][act])
        resumed_from[name] = shorter_steps(shorter)
        return checkpoint, None if reused else time.perf_counter() - start  # a reused run's time is not known

    with ThreadPoolExecutor(jobs) as pool:
        trained = list(pool.map(train_arm, runs))
    torch.set_num_threads(1)
    rows = []
    for (labels, dataset, seed), (checkpoint, train_s) in zip(runs, trained, strict=True):
        start = time.perf_counter()
        result = evaluate_checkpoint(checkpoint, env_cfg, episodes_eval)
        eval_s = time.perf_counter() - start
        fit = training_fit(checkpoint, dataset, every=FIT_EVERY[policy])
        rows.append(
            {
                "env": env, "policy": policy, "commit": commit, "labels": labels,
                "idm_context": k if labels == "idm" else None,
                "pull_to_observation": pull if labels == "idm" and pull else None,
                "seed": seed,
                "success_rate": result["pc_success"] / 100.0, "avg_sum_reward": result["avg_sum_reward"],
                "episodes": episodes_eval, "act": act, "act_steps": act_steps, "train_s": train_s,
                # train_s then counts only the steps after those of the run it resumed
                "resumed_from_steps": resumed_from.get(checkpoint.parents[2].name),
                "eval_s": eval_s,
                "training_fit_r2_per_dim": fit,
            }
        )  # fmt: skip
        print(json.dumps(rows[-1]), flush=True)
    return rows, quality


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=list(ENVS), choices=list(ENVS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--eval_episodes", type=int, default=50)
    parser.add_argument("--jobs", type=int, default=2, help="ACT runs trained at a time (one thread each)")
    parser.add_argument("--idm_context", type=int, default=1, help="the IDM's window k (--policy.idm_context)")
    parser.add_argument(
        "--arms", nargs="*", default=["true", "idm"], choices=["true", "idm"],
        help="ACT arms to train (none: measure the labels only)",
    )  # fmt: skip
    parser.add_argument(
        "--idm_keys", nargs="*", default=[], help="the observation keys the IDM reads (default: all of them)"
    )
    parser.add_argument("--policy", default="act", choices=list(POLICY_SETTINGS), help="LeRobot's policy to train")
    parser.add_argument(
        "--act", default=DEFAULT_ACT, choices=list(ACT_SETTINGS), help="how ACT plays its chunks (see ACT_SETTINGS)"
    )
    parser.add_argument(
        "--steps", "--act_steps", dest="act_steps", type=int, default=None,
        help="the policy's training steps (default: per env)",
    )  # fmt: skip
    parser.add_argument(
        "--pull_to_observation", type=float, default=0.0, help="lerobot-iupe-relabel's --pull_to_observation"
    )
    args = parse_with_folders(parser, "outputs/measure-downstream")
    work, command = Path(args.work), command_line()
    for env in args.envs:
        rows, quality = measure(
            env, work, args.seeds, args.eval_episodes, args.jobs, args.idm_context, args.arms, args.idm_keys,
            args.act if args.policy == "act" else "lerobot", args.act_steps, args.pull_to_observation, args.policy,
        )  # fmt: skip
        if rows:
            key = ("env", "policy", "commit", "labels", "idm_context", "pull_to_observation", "seed", "act")
            update(Path(args.out), "downstream", rows, command, key=(*key, "act_steps"))
        label_key = ("env", "idm_context", "idm_reads", "pull_to_observation")
        update(Path(args.out), "downstream_labels", [quality], command, key=label_key)
    print(render(Path(args.out)))


if __name__ == "__main__":
    main()
