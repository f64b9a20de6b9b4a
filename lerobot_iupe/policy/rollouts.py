"""A policy played in its env: the IUPE cycle's rollouts, the selection episodes of every plugin policy, any
LeRobot env type, several envs at once with batched inference."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_iupe.data.compat import check_compatible, dataset_spec, env_spec
from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.envs.configs import env_config_from_settings, env_observation, env_observation_keys, make_envs
from lerobot_iupe.envs.rollout import run_episodes


class PolicyRollouts:
    """Plays ``policy`` (a plugin policy: ``IUPEPolicy`` or ``ILPOPolicy``, which both give ``layout``,
    ``push_history``, ``rollout_actions``, ``averaged_weights`` and ``device_of_weights``) in the env set by
    ``use_env``, on the layouts set by ``use_layouts``."""

    def __init__(self, policy: nn.Module, context: int = 0):
        self.policy, self.config = policy, policy.config
        self.context = context  # the transitions' windows: frames t-k … t+1+k around each action (Transitions)
        self.envs: list = []  # rollout envs, created once and reused by every cycle
        self.layouts: list[int] = []  # maze: the layout ids rollouts cycle through (--policy.rollout_layouts)
        self.env_cfg = None  # the rollout env
        self.env_keys: list[str] = []  # the env observations the policy reads (features_map: env key → its key)

    def use_layouts(self, meta) -> None:
        """Mazes: the expert dataset's layouts that rollouts and selection episodes play (the last K of them)."""
        cfg = self.config
        layouts = [int(i) for i in read_iupe_meta(meta.root).get("layout_ids", [])]
        if cfg.rollout_layouts and cfg.rollout_layouts >= len(set(layouts)):
            raise ValueError(
                f"--policy.rollout_layouts={cfg.rollout_layouts} must be below the number of distinct layouts of the "
                f"expert dataset at {meta.root} ({len(set(layouts))}), so that some are never rolled out on"
                + ("" if layouts else ": it records none (meta/iupe.json layout_ids; maze datasets only)")
            )
        self.layouts = list(dict.fromkeys(layouts))[-cfg.rollout_layouts :] if cfg.rollout_layouts else layouts

    def use_dataset_env(self, meta, what: str = "the expert dataset"):
        """Play the env of the policy's settings (``env_settings``), checked against the observations of the dataset
        ``meta`` (``what`` names it in errors); returns its config."""
        cfg = self.config
        if cfg.env_settings is None:
            raise ValueError(
                f"{what} at {meta.root} records no environment (meta/iupe.json); "
                "pass --env.type=<its env> (and --env.<field>=… as for lerobot-eval)"
            )
        env_cfg = env_config_from_settings(cfg.env_settings)
        for key in cfg.observation_keys:
            check_compatible(env_spec(env_cfg, key), dataset_spec(meta, key, f"{what} at {meta.root}"))
        self.use_env(env_cfg)
        return env_cfg

    def use_env(self, env_cfg) -> None:
        """Roll out in ``env_cfg`` (any LeRobot env type whose ``features_map`` gives the policy's observations)."""
        env_key_of = {v: k for k, v in env_observation_keys(env_cfg).items()}
        missing = [k for k in self.config.observation_keys if k not in env_key_of]
        if missing:
            raise ValueError(
                f"env {env_cfg.type} gives no {missing} (its observations: {sorted(env_key_of)}); "
                "the policy reads what the expert dataset holds"
            )
        self.env_cfg, self.env_keys, self.envs = env_cfg, [env_key_of[k] for k in self.config.observation_keys], []

    @torch.no_grad()
    def play(
        self, episodes: int, seed: int, explore: bool, generator: torch.Generator | None = None
    ) -> tuple[list[Transitions], np.ndarray, np.ndarray, np.ndarray]:
        """The policy model in ``episodes`` envs at once (batched inference), one episode each, env ``i`` seeded
        ``seed + i`` (mazes: the expert dataset's layouts in turn); in eval mode (batch-norm statistics kept).
        Returns each episode's transitions (windows of ``context``), goal reached (v_e), return and the env's own
        success.
        Envs are made once by LeRobot's ``make_env`` (any LeRobot env type) and reused by every cycle."""
        policy, device = self.policy, self.policy.device_of_weights
        if len(self.envs) < episodes:
            self.envs += make_envs(self.env_cfg, episodes - len(self.envs))
        envs = self.envs[:episodes]
        continuous = self.config.is_continuous

        history: Tensor | None = None  # every env's last n_obs_steps observations (E, n, …)

        def act(observations: list[dict], active: list[int]) -> list:
            nonlocal history
            obs = torch.as_tensor(np.stack([self.observation(o) for o in observations]), device=device)
            if history is None:  # the first step: every env is active
                history = policy.push_history(None, obs)
            else:
                rows = torch.as_tensor(active, device=device)
                history[rows] = policy.push_history(history[rows], obs)
            actions = policy.rollout_actions(history[active], explore, generator)
            actions = actions.cpu().numpy()
            return list(actions) if continuous else [int(a) for a in actions]

        seeds = [seed + i for i in range(episodes)]
        options = [{"layout_id": self.layouts[s % len(self.layouts)]} if self.layouts else None for s in seeds]
        was_training = policy.training
        policy.eval()
        with policy.averaged_weights():  # the policy acts with its weight average (ema_decay), as it is saved
            played = run_episodes(envs, act, seeds, options)
        policy.train(was_training)
        transitions = []
        for episode in played:
            observations = np.stack([self.observation(o) for o in episode.observations])
            if continuous:
                actions = np.asarray(episode.actions, dtype=np.float32).reshape(len(episode), -1)
            else:
                actions = np.asarray(episode.actions, dtype=np.int64)
            transitions.append(Transitions.of_episode(observations, actions, self.context))
        successes = np.array([e.goal_reached for e in played])  # v_e: the goal reached at some step
        returns = np.array([e.total_reward for e in played])
        return transitions, successes, returns, np.array([e.success for e in played])

    def observation(self, env_observation_dict: dict) -> np.ndarray:
        """The policy's input from one env observation: its keys (cameras (H, W, C) → (C, H, W)) joined in
        observation_keys order."""
        layout = self.policy.layout
        parts = [np.asarray(env_observation(env_observation_dict, k)) for k in self.env_keys]
        parts = [p.transpose(2, 0, 1) if visual else p for p, visual in zip(parts, layout.visual, strict=True)]
        return layout.join([p[None] for p in parts])[0]
