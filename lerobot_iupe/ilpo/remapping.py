"""ILPO inside ``lerobot-train``, top to bottom:

1. every step (``ILPOPolicy.forward``): one LPN step on expert pairs; which latent action wins each pair and how π
   spreads over them are counted, so that a collapse onto few latent actions shows in the logs;
2. after lerobot-train's last step (``step_done``): ``remap`` — the LPN frozen, a fresh ARN drawn from the run's
   seed, ``remap_steps`` env steps, each
   acting greedily (argmax_z π, then the ARN's action) or, with probability ``remap_epsilon``, uniformly at random;
   each transition labelled with z* (the latent action that explains it best) into a replay buffer, and one ARN
   step on a batch from it per env step once it holds a batch.

Everything counted — env steps, the ARN's online accuracy, latent usage — goes to ``ilpo_remapping.json`` beside
the checkpoint; ``ilpo_training_state.pt`` holds the step count, so that ``--resume=true`` goes on exactly.
"""

import copy
import json
import logging
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from torch import Tensor, nn

from lerobot_iupe.data.readers import ExpertFrames
from lerobot_iupe.data.video import default_video_backend
from lerobot_iupe.envs.configs import make_envs
from lerobot_iupe.ilpo.latent_model import ActionRemappingNetwork
from lerobot_iupe.policy.algorithm import selects
from lerobot_iupe.policy.rollouts import PolicyRollouts
from lerobot_iupe.policy.train_run import lerobot_train_config, read_no_cameras_in_lerobot_train, resuming

log = logging.getLogger("lerobot_iupe")
STATE_FILE = "ilpo_training_state.pt"
SUMMARY_FILE = "ilpo_remapping.json"


def arn_step(arn: nn.Module, optimizer: torch.optim.Optimizer, frames: Tensor, z: Tensor, actions: Tensor) -> float:
    """One step of the action remapping network on (s, z*) → the executed action (its head's loss)."""
    arn.train()
    loss = arn.head.loss(arn(frames, z), actions)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    arn.eval()
    return float(loss.detach())


class ILPOTrainer:
    """ILPO's two phases on ``policy`` (an ``ILPOPolicy``) with the expert dataset ``dataset_meta``."""

    def __init__(self, policy: nn.Module, dataset_meta: LeRobotDatasetMetadata, seed: int):
        self.policy, self.config, self.dataset_meta, self.seed = policy, policy.config, dataset_meta, seed
        train_cfg = lerobot_train_config()
        self.total_steps = train_cfg.steps if train_cfg is not None else None  # None: policy.remap() by hand
        self.step = 0
        self.summary: dict | None = None  # the remapping's record, once it ran
        self.selected_arn: dict[str, Tensor] | None = None
        self.rollouts = PolicyRollouts(policy)
        n_latent = self.config.n_latent
        self.wins, self.policy_mass = torch.zeros(n_latent), torch.zeros(n_latent)
        self._expert: ExpertFrames | None = None
        if cameras := read_no_cameras_in_lerobot_train():
            log.info(f"ILPO: lerobot-train's loader reads no camera ({', '.join(cameras)}): frames come from the cache")
        saved = Path(self.config.pretrained_path or "") / STATE_FILE
        if self.config.pretrained_path and resuming() and saved.exists():
            state = torch.load(saved, weights_only=True)
            self.step, self.seed = int(state["step"]), int(state["seed"])
            self.wins, self.policy_mass = state["wins"], state["policy_mass"]
            log.info(f"ILPO: continuing from step {self.step} of {saved.parent}")

    def expert_frames(self) -> ExpertFrames:
        if self._expert is None:
            if self.config.threads:
                torch.set_num_threads(self.config.threads)
            meta = self.dataset_meta
            dataset = LeRobotDataset(meta.repo_id, root=meta.root, video_backend="pyav")
            device = self.policy.device_of_weights
            self._expert = ExpertFrames(
                dataset, self.config.observation_keys, False, device, self.config.layout, default_video_backend()
            )
            log.info(f"ILPO: expert dataset ready, {len(self._expert.episodes)} frames")
            if self.config.normalize and not self.config.is_image:
                self.scale_differences(self._expert)
        return self._expert

    def scale_differences(self, expert: ExpertFrames) -> None:
        """``normalize``: each value's std of s_{t+1} − s_t over the expert's pairs (normalised states)."""
        rows = np.flatnonzero(expert.episodes[:-1] == expert.episodes[1:])
        self.policy.fit_difference_scale(expert.states[rows], expert.states[rows + 1])

    def count_latents(self, winners: Tensor, probabilities: Tensor) -> None:
        """Tally which latent action explains each expert pair best and π's mass on each."""
        self.wins += torch.bincount(winners.detach().cpu(), minlength=len(self.wins)).float()
        self.policy_mass += probabilities.detach().float().sum(0).cpu()

    def step_done(self) -> None:
        self.step += 1
        if self.total_steps is not None and self.step == self.total_steps and self.summary is None:
            self.remap()

    # ------------------------------------------------------------ online remapping

    def use_env(self):
        """The remapping env (checked against the expert data) and the maze layouts it plays."""
        env_cfg = self.rollouts.use_dataset_env(self.dataset_meta)
        self.rollouts.use_layouts(self.dataset_meta)
        return env_cfg

    def remap(self) -> dict:
        cfg, policy = self.config, self.policy
        env_cfg = self.use_env()
        env = make_envs(env_cfg, 1)[0]
        device = policy.device_of_weights
        rng = np.random.default_rng([self.seed, 2])
        # A fresh ARN drawn from the run's seed: the remapping then depends on the LPN and the seed alone, so a
        # finished run extended with --resume=true remaps as the longer run would have.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed % 2**62 + 2)
            policy.arn.load_state_dict(ActionRemappingNetwork(cfg).state_dict())
        self.selected_arn = None
        arn_optimizer = torch.optim.Adam(policy.arn.parameters(), lr=cfg.remap_lr)
        size = min(cfg.remap_buffer_size, cfg.remap_steps)
        buffer_frames = torch.zeros(size, policy.layout.size, device=device)
        buffer_z = torch.zeros(size, dtype=torch.long, device=device)
        buffer_actions = torch.zeros((size, cfg.action_dim) if cfg.is_continuous else size, device=device)
        if not cfg.is_continuous:
            buffer_actions = buffer_actions.long()
        first_seed = 1_000_000 + self.seed * 100_003  # apart from the evaluation's seeds (500,000…)
        episode, stored, correct, records, best = 0, 0, [], [], (-1.0, -1.0)
        selection_env_steps = 0

        def reset():
            nonlocal episode
            layouts = self.rollouts.layouts
            options = {"layout_id": layouts[episode % len(layouts)]} if layouts else None
            observation, _ = env.reset(seed=first_seed + episode, options=options)
            episode += 1
            return self.frames(observation)

        was_training = policy.training
        policy.eval()
        frames = reset()
        for t in range(cfg.remap_steps):
            with torch.no_grad():
                greedy = policy.act(frames, explore=False)[0]
            if rng.random() < cfg.remap_epsilon:
                action = self.random_action(env, rng)
            else:
                action = greedy.cpu().numpy() if cfg.is_continuous else int(greedy)
            observation, _, terminated, truncated, _ = env.step(action)
            next_frames = self.frames(observation)
            z = policy.explaining_latents(frames, next_frames)
            action_tensor = torch.as_tensor(np.asarray(action), device=device)
            with torch.no_grad():  # the ARN's guess before it learns this transition: an online, held-out score
                guess = policy.arn.head.mode(policy.arn(frames, z))[0]
            if cfg.is_continuous:
                correct.append(float((guess - action_tensor).square().mean()))
            else:
                correct.append(float(int(guess) == action))
            slot = stored % size
            buffer_frames[slot], buffer_z[slot], buffer_actions[slot] = frames[0], z[0], action_tensor
            stored += 1
            if stored >= cfg.remap_batch_size:
                batch = torch.as_tensor(rng.integers(min(stored, size), size=cfg.remap_batch_size), device=device)
                arn_step(policy.arn, arn_optimizer, buffer_frames[batch], buffer_z[batch], buffer_actions[batch])
            frames = reset() if terminated or truncated else next_frames
            if cfg.selection_episodes and (t + 1) % cfg.selection_every == 0:
                record, played = self.select(t + 1, first_seed + 50_000, best)
                selection_env_steps += played
                if record["selected"]:
                    best = (record["selection_env_success_rate"], record["selection_goal_rate"])
                records.append(record)
        policy.train(was_training)
        env.close()
        score = "arn_online_mse" if cfg.is_continuous else "arn_online_accuracy"
        window = correct[-min(len(correct), 200) :]
        z_usage = torch.bincount(buffer_z[: min(stored, size)].cpu(), minlength=cfg.n_latent).float()
        self.summary = {
            "lpn_steps": self.step,
            "remap_env_steps": cfg.remap_steps,
            "remap_episodes": episode,
            "selection_env_steps": selection_env_steps,
            score: float(np.mean(window)),
            f"{score}_all": float(np.mean(correct)),
            "z_star_usage": (z_usage / z_usage.sum()).tolist(),
            "expert_winner_usage": (self.wins / self.wins.sum().clamp_min(1)).tolist(),
            "expert_policy_usage": (self.policy_mass / self.policy_mass.sum().clamp_min(1)).tolist(),
            "selection": records,
        }
        log.info(
            f"ILPO remapping: {cfg.remap_steps} env steps in {episode} episodes, ARN {score} (last 200 steps) "
            f"{self.summary[score]:.3f}; z* usage {np.round(self.summary['z_star_usage'], 3).tolist()}, "
            f"expert winners {np.round(self.summary['expert_winner_usage'], 3).tolist()}"
            + (f"; selection played {selection_env_steps} env steps" if records else "")
        )
        return self.summary

    def select(self, step: int, seed: int, best: tuple[float, float]) -> tuple[dict, int]:
        """Play the selection episodes as lerobot-eval plays; keep the ARN if it is the best so far."""
        explore = self.config.eval_mode == "sample"
        episodes, goals, _, env_successes = self.rollouts.play(self.config.selection_episodes, seed, explore)
        judged = (float(env_successes.mean()), float(goals.mean()))
        selected = selects(judged[0], judged[1], best)
        if selected:
            self.selected_arn = {f"arn.{k}": v.clone() for k, v in copy.deepcopy(self.policy.arn.state_dict()).items()}
        record = {
            "step": step, "selection_episodes": self.config.selection_episodes,
            "selection_env_success_rate": judged[0], "selection_goal_rate": judged[1], "selected": selected,
        }  # fmt: skip
        return record, int(sum(len(e) for e in episodes))

    def frames(self, observation: dict) -> Tensor:
        """One env observation as the networks read it: (1, size)."""
        joined = torch.as_tensor(self.rollouts.observation(observation)[None], device=self.policy.device_of_weights)
        return self.policy.flat(joined)

    def random_action(self, env, rng: np.random.Generator):
        """A uniformly random real action, from this run's stream."""
        cfg = self.config
        if not cfg.is_continuous:
            return int(rng.integers(cfg.n_actions))
        return rng.uniform(cfg.action_low, cfg.action_high).astype(np.float32)

    # ------------------------------------------------------------ checkpoints

    def save(self, directory: Path) -> None:
        torch.save(
            {"step": self.step, "seed": self.seed, "wins": self.wins, "policy_mass": self.policy_mass},
            directory / STATE_FILE,
        )
        if self.summary is not None:
            (directory / SUMMARY_FILE).write_text(json.dumps(self.summary, indent=1))
