"""The IUPE cycle, top to bottom, as it runs inside ``lerobot-train`` (one optimizer step = one policy step on an
expert batch; ``update()`` after each step is LeRobot's only in-loop hook):

1. ``start`` (first step): check the inputs, load the pre-demonstrations I_pre, I^s = I_pre, train the IDM on it;
2. ``labels`` (every step): the IDM labels the expert pairs (s_t, s_{t+1}) — or, with ``idm_context`` k, the
   frames s_{t-k} … s_{t+1+k} — one draw per row when exploring, the mode otherwise, and the policy model takes a
   step on those labels;
3. ``end_cycle`` (every ``cycle_steps`` steps): roll out the policy, record (s_t, a_t, s_{t+1}) of the same step
   and whether the goal was reached (``Episode.goal_reached``), select the model by the env's own success and then
   the goal (``algorithm.selects``), rebuild I^s by the sampling rule (or, for BCO(α), I_pre plus the rollouts)
   and retrain the IDM on it.

Everything the cycle needs to go on exactly where it stopped is a ``TrainingState``, saved beside the checkpoint
(``iupe_training_state.pt``, plain tensors and numbers) with one record per cycle (``iupe_cycles.jsonl``).
"""

from __future__ import annotations

import copy
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.utils.constants import ACTION
from torch import Tensor, nn

from lerobot_iupe.data.compat import check_compatible, dataset_spec, env_spec
from lerobot_iupe.data.readers import ExpertFrames, load_transitions
from lerobot_iupe.data.storage import is_dataset
from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.data.video import default_video_backend
from lerobot_iupe.policy.algorithm import (
    ActionCells,
    build_sampled_set,
    held_out_split,
    selects,
    success_action_distribution,
)
from lerobot_iupe.policy.idm_fit import fit_idm
from lerobot_iupe.policy.joint_fit import JointFit
from lerobot_iupe.policy.rollouts import PolicyRollouts
from lerobot_iupe.policy.threads import use_cpu_runtime
from lerobot_iupe.policy.train_run import read_no_cameras_in_lerobot_train, resuming
from lerobot_iupe.policy.training_state import CYCLES_FILE, TRAINING_STATE_FILE, TrainingState

log = logging.getLogger("lerobot_iupe")


class IUPETrainer:
    """Runs the cycle on ``policy`` (an ``IUPEPolicy``: its IDM and policy model) with the expert dataset
    ``dataset_meta``. The policy builds and holds its trainer; this module does not import the policy's, so
    imports run one way."""

    def __init__(self, policy: nn.Module, dataset_meta: LeRobotDatasetMetadata, seed: int):
        self.policy, self.config, self.dataset_meta, self.seed = policy, policy.config, dataset_meta, seed
        # --resume=true continues the saved state exactly; --policy.path alone starts a new run (LeRobot's fine-tuning).
        self.resume = resuming()
        self.prior_ready = False  # a supervised IDM's linear part is fitted on the first step (linear_prior.py)
        self.state: TrainingState | None = None
        self.stats: dict[str, float] = {}  # the latest losses and rates, logged by lerobot-train
        self.selected_weights: dict[str, Tensor] | None = None  # the model ``algorithm.selects`` kept so far
        # The rollout env (set by check_inputs), its envs and layouts; transitions windowed as the IDM reads them.
        self.rollouts = PolicyRollouts(policy, self.config.idm_context or 0)
        self.cells: ActionCells | None = None  # continuous actions: the sampling rule's action classes
        self._expert: ExpertFrames | None = None
        self._joint_fit: JointFit | None = None  # the arm model's fit (supervised, joint actions)
        if cameras := read_no_cameras_in_lerobot_train():
            log.info(f"IUPE: lerobot-train's loader reads no camera ({', '.join(cameras)}): frames come from the cache")

    @property
    def cycles(self) -> list[dict]:
        return self.state.cycles if self.state else []

    @property
    def device(self) -> torch.device:
        return self.policy.device_of_weights

    # ------------------------------------------------------------ 1. start

    def check_inputs(self) -> LeRobotDataset:
        """Every check that can fail, before any training; returns the pre-demonstrations."""
        cfg = self.config
        self.rollouts.use_dataset_env(self.dataset_meta)
        if cfg.pre_demos_repo_id is None:
            raise ValueError("--policy.pre_demos_repo_id is required (random pre-demonstrations with actions)")
        root = cfg.pre_demos_root
        if root is not None and not is_dataset(root):
            raise FileNotFoundError(f"--policy.pre_demos_root={root} is not a LeRobot dataset (no meta/info.json)")
        pre = LeRobotDataset(cfg.pre_demos_repo_id, root=root, video_backend="pyav")
        if ACTION not in pre.features:
            raise ValueError(
                f"the pre-demonstrations {cfg.pre_demos_repo_id} have no 'action' column; "
                "collect them with lerobot-iupe-collect --agent=random"
            )
        for key in cfg.observation_keys:
            pre_spec = dataset_spec(pre.meta, key, f"the pre-demonstrations {cfg.pre_demos_repo_id}")
            check_compatible(env_spec(self.rollouts.env_cfg, key), pre_spec)
        continuous_actions = pre.meta.features[ACTION]["dtype"].startswith("float")
        if continuous_actions != cfg.is_continuous:
            kind = {True: "continuous", False: "discrete"}
            raise ValueError(
                f"the pre-demonstrations {cfg.pre_demos_repo_id} have {kind[continuous_actions]} actions but env "
                f"{self.rollouts.env_cfg.type} has {kind[cfg.is_continuous]} ones"
            )
        self.use_layouts()
        return pre

    def use_layouts(self) -> None:
        self.rollouts.use_layouts(self.dataset_meta)  # mazes: the layouts rollouts and selection episodes play

    def use_env(self, env_cfg) -> None:
        self.rollouts.use_env(env_cfg)

    def start(self) -> None:
        cfg = self.config
        pre_dataset = self.check_inputs()
        use_cpu_runtime(self.config.threads)
        rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
        pre = load_transitions(pre_dataset, cfg.observation_keys, "pyav", cfg.layout, cfg.idm_context or 0)
        if cfg.is_continuous:  # fitted again identically on resume (own seed)
            self.cells = ActionCells.fit(pre.actions, cfg.action_cells, cfg.action_low, cfg.action_high, self.seed)
        # Its own stream, so that a resumed run holds out the same transitions without saving them.
        train_part, held_part = held_out_split(len(pre), np.random.default_rng([self.seed, rank, 1]))
        pre, pre_held = pre.take(train_part), pre.take(held_part)
        size = cfg.sampled_set_size or len(pre)
        idm_optimizer = torch.optim.Adam(self.policy.idm_parameters(), lr=cfg.idm_lr)
        self.state = state = self.new_state(rank, pre, pre_held, size, idm_optimizer)
        log.info(
            f"IUPE: {len(pre) + len(pre_held)} pre-demonstration transitions ({len(pre_held)} held out to score "
            f"the IDM), I^s size {size}, env {self.rollouts.env_cfg.type}"
        )
        if self.resumed():
            return
        start = time.perf_counter()
        self.train_idm(pre, pre_held)
        state.idm_s += time.perf_counter() - start

    def start_selection(self) -> None:
        """A supervised run that selects (``--policy.selection_episodes=N``): its env and a state that counts the
        steps and keeps the best model; no pre-demonstrations, no IDM cycle (LeRobot's optimizer trains both)."""
        self.rollouts.use_dataset_env(self.dataset_meta, "the dataset")
        self.use_layouts()
        rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
        self.state = self.new_state(rank, None, None, 0, None)
        self.resumed()

    def new_state(self, rank: int, pre, pre_held, size: int, idm_optimizer) -> TrainingState:
        """A fresh training state: this run's random streams (the torch one only where the policy runs on CPU)."""
        state = TrainingState(
            seed=self.seed,
            rank=rank,
            pre=pre,
            pre_held=pre_held,
            sampled_set_size=size,
            rng=np.random.default_rng([self.seed, rank]),
            torch_rng=torch.Generator(device="cpu").manual_seed((self.seed * 1000 + rank) % 2**63),
            idm_optimizer=idm_optimizer,
        )
        if state.torch_rng.device != self.device:
            state.torch_rng = None
        return state

    def resumed(self) -> bool:
        """--resume=true: restore the saved state beside the checkpoint, if there is one."""
        cfg, state = self.config, self.state
        saved = Path(cfg.pretrained_path) / TRAINING_STATE_FILE if cfg.pretrained_path and self.resume else None
        if saved is None or not saved.exists():
            return False
        self.restore(torch.load(saved, map_location=self.device, weights_only=True))
        log.info(f"IUPE: continuing from cycle {state.cycle} (step {state.step}) of {saved.parent}")
        return True

    def restore(self, saved: dict) -> None:
        """Go on where the saved run stopped: the loaded weights are its selected model; the current model becomes
        its latest one (LeRobot's restored optimizer state belongs to those)."""
        self.selected_weights = copy.deepcopy(self.policy.state_dict())
        self.policy.load_state_dict(saved["latest_weights"])
        self.policy.averaged = saved.get("averaged_weights")  # None: no average (or a state saved before it)
        self.state.restore(saved)
        self.seed = self.state.seed

    def expert_frames(self) -> ExpertFrames:
        if self._expert is None:
            if self.config.supervised:  # the IUPE cycle sets them in start()
                use_cpu_runtime(self.config.threads)
            meta = self.dataset_meta
            dataset = LeRobotDataset(meta.repo_id, root=meta.root, video_backend="pyav")
            cfg = self.config
            self._expert = ExpertFrames(
                dataset, cfg.observation_keys, cfg.supervised, self.device, cfg.layout, default_video_backend()
            )
            log.info(f"IUPE: expert dataset ready, {len(self._expert.episodes)} frames")
        return self._expert

    def joint_idm_batch(self, rows: np.ndarray) -> tuple[Tensor, Tensor | None, np.ndarray]:
        """The linear-first model (fitted on the first call): the batch's rows its networks train on, their state
        windows and their camera frames (None where no dimension reads a camera)."""
        if self._joint_fit is None:
            self._joint_fit = JointFit(self.policy, self.expert_frames(), self.resume)
        rows = self._joint_fit.training_rows(rows)
        return self._joint_fit.windows(rows), self._joint_fit.camera(rows), rows

    def update_joint_gate(self) -> None:
        if self._joint_fit is not None:
            self._joint_fit.update_gate()

    # ------------------------------------------------------------ 2. every step

    def labels(self, window: Tensor) -> tuple[Tensor, Tensor | None]:
        """The IDM's labels of expert windows (B, 2k+2, …: frames t-k … t+1+k; k = 0 the pair), in eval mode
        (batch-norm layers keep their statistics), and their spread: what the policy model's loss takes
        (``head.labels``)."""
        if self.state is None:
            self.start()
        policy = self.policy
        was_training = policy.training
        policy.eval()
        with torch.no_grad():
            output = policy.idm_window_output(window)
        policy.train(was_training)
        head = policy.idm_head
        drawn = head.choose(output, self.config.exploration, self.state.torch_rng)
        self.stats["label_non_map"] = head.spread(output, drawn)
        return head.labels(output, drawn, self.config.exploration)

    def step_done(self) -> None:
        if self.state is None:  # supervised: nothing has started it (the IUPE cycle starts in labels())
            self.start_selection()
        self.state.step += 1
        if self.state.step % self.config.cycle_steps == 0:
            self.end_selection_cycle() if self.config.supervised else self.end_cycle()

    # ------------------------------------------------------------ 3. every cycle

    def end_cycle(self) -> None:
        cfg, state = self.config, self.state
        state.cycle += 1
        seed = self.episode_seeds + state.cycle * cfg.rollout_episodes
        start = time.perf_counter()
        rollouts = self.rollout(cfg.rollout_episodes, seed, explore=cfg.exploration)
        episodes, successes, returns, env_successes = rollouts
        state.rollouts_s += time.perf_counter() - start
        success_rate, env_success_rate = float(successes.mean()), float(env_successes.mean())
        judged = {"goal": success_rate, "env": env_success_rate}
        if cfg.separate_selection_episodes:
            start = time.perf_counter()
            judged = self.selection_rates(cfg.separate_selection_episodes)
            state.selection_s += time.perf_counter() - start
        selected = self.keep_if_best(judged)
        pre = state.pre
        good = [e for e, ok in zip(episodes, successes, strict=True) if ok]
        # The IDM is scored on transitions it is not trained on: a tenth of this cycle's rollout transitions that
        # enter I^s (and I_pre's held-out part), split off before I^s draws copies.
        if cfg.sampling:
            successful = Transitions.concat(good) if good else pre.take(np.arange(0))
            classes = successful.actions if self.cells is None else self.cells.assign(successful.actions)
            successful, new_held = self._split(successful, classes)
            if self.cells is None:
                p_success = success_action_distribution([e.actions for e in episodes], successes, cfg.n_actions)
                sampled = build_sampled_set(
                    pre, successful, p_success, state.sampled_set_size, state.rng,
                    max_success_share=cfg.max_success_share,
                )  # fmt: skip
            else:  # continuous: the rule on action cells
                classes = [self.cells.assign(e.actions) for e in episodes]
                p_success = success_action_distribution(classes, successes, self.cells.k)
                sampled = build_sampled_set(
                    pre, successful, p_success, state.sampled_set_size, state.rng,
                    self.cells.assign(pre.actions), self.cells.assign(successful.actions), cfg.max_success_share,
                )  # fmt: skip
        else:  # BCO(α): the IDM learns from I_pre and all of the policy's latest rollouts
            rollouts, new_held = self._split(Transitions.concat(episodes))
            sampled = Transitions.concat([pre, rollouts])
        held = Transitions.concat([state.pre_held, new_held])
        start = time.perf_counter()
        self.train_idm(sampled, held, new_held)
        state.idm_s += time.perf_counter() - start
        self.stats.update({"success_rate": success_rate, "rollout_return": float(returns.mean())})
        record = {
            "cycle": state.cycle,
            "step": state.step,
            "rollout_seed": seed,
            "success_rate": success_rate,
            "env_success_rate": env_success_rate,
            "return": float(returns.mean()),
            "selection_episodes": cfg.separate_selection_episodes or cfg.rollout_episodes,
            "selection_env_success_rate": judged["env"],
            "selection_goal_rate": judged["goal"],
            "selected": selected,
            "best_success": state.best_success,
            "sampled_set_size": len(sampled),
            "idm_held_out": len(held),
            "successful_transitions": int(sum(len(e) for e in good)),
            "rollout_env_steps": int(sum(len(e) for e in episodes)),
            "selection_env_steps": judged.get("env_steps", 0),
            self.idm_metric: self.stats[self.idm_metric],
            "label_non_map": self.stats.get("label_non_map", 0.0),
            "rollouts_s": state.rollouts_s,
            "idm_s": state.idm_s,
            "selection_s": state.selection_s,
        }
        state.cycles.append(record)
        log.info(
            f"IUPE cycle {state.cycle}: success r={success_rate:.2f} (env's {env_success_rate:.2f}) "
            f"return={record['return']:.1f} "
            f"IDM {self.idm_metric}={record[self.idm_metric]:.3f} label spread={record['label_non_map']:.3f} "
            f"|I^s|={len(sampled)} selection on {record['selection_episodes']} episodes: env's "
            f"{judged['env']:.2f}, goal {judged['goal']:.2f} (best {state.best_env_success:.2f}, "
            f"{state.best_success:.2f}{', selected' if selected else ''}) "
            f"time so far: rollouts {state.rollouts_s:.2f}s selection {state.selection_s:.2f}s IDM {state.idm_s:.2f}s"
        )

    def end_selection_cycle(self) -> None:
        """Supervised: play the selection episodes and keep the model if it is the best so far."""
        state = self.state
        state.cycle += 1
        start = time.perf_counter()
        judged = self.selection_rates(self.config.separate_selection_episodes)
        state.selection_s += time.perf_counter() - start
        selected = self.keep_if_best(judged)
        state.cycles.append(
            {
                "cycle": state.cycle,
                "step": state.step,
                "selection_episodes": self.config.separate_selection_episodes,
                "selection_env_success_rate": judged["env"],
                "selection_goal_rate": judged["goal"],
                "selected": selected,
                "best_success": state.best_success,
                "selection_env_steps": judged.get("env_steps", 0),
                "selection_s": state.selection_s,
            }
        )
        log.info(
            f"BC (supervised), step {state.step}: selection on {self.config.separate_selection_episodes} episodes: "
            f"env's {judged['env']:.2f}, goal {judged['goal']:.2f}{', selected' if selected else ''}"
        )

    def keep_if_best(self, judged: dict[str, float]) -> bool:
        """Select the current model if its rates beat the best so far (``algorithm.selects``); whether it did."""
        state = self.state
        selected = selects(judged["env"], judged["goal"], (state.best_env_success, state.best_success))
        if selected:
            state.best_env_success, state.best_success = judged["env"], judged["goal"]
            with self.policy.averaged_weights():  # the model that was judged
                self.selected_weights = copy.deepcopy(self.policy.state_dict())
        return selected

    def selection_rates(self, episodes: int) -> dict[str, float]:
        """The goal and env-success rates of ``episodes`` played as lerobot-eval plays (``eval_mode``), from the
        same start seeds every cycle (apart from the rollouts' and the benchmark's evaluation seeds)."""
        sample = self.config.eval_mode == "sample"
        played, goals, _, env_successes = self.rollout(episodes, self.episode_seeds + 50_000, explore=sample)
        steps = sum(len(e) for e in played)
        return {"goal": float(goals.mean()), "env": float(env_successes.mean()), "env_steps": steps}

    @property
    def episode_seeds(self) -> int:
        """Where this run's env seeds start (≥ 1,000,000, one range per rank): the rollouts from here on, cycle
        after cycle, and the selection episodes always at 50,000 past it."""
        return 1_000_000 * (1 + self.state.rank) + self.seed * 100_003

    def rollout(
        self, episodes: int, seed: int, explore: bool
    ) -> tuple[list[Transitions], np.ndarray, np.ndarray, np.ndarray]:
        """``PolicyRollouts.play`` with this run's torch stream."""
        return self.rollouts.play(episodes, seed, explore, self.state.torch_rng if self.state else None)

    @property
    def idm_metric(self) -> str:
        """How the IDM is scored on held-out I^s: label agreement (discrete) or R² (continuous)."""
        return "idm_r2" if self.config.is_continuous else "idm_accuracy"

    def _split(self, data: Transitions, classes: np.ndarray | None = None) -> tuple[Transitions, Transitions]:
        train, held = held_out_split(len(data), self.state.rng, classes=classes)
        return data.take(train), data.take(held)

    def train_idm(self, data: Transitions, held_out: Transitions, own_held_out: Transitions | None = None) -> None:
        """Train the IDM on I^s (``data``, all of it) and score it on ``held_out`` (``idm_metric``), transitions
        of which ``data`` holds no copy; a linear part's gate is judged on ``own_held_out``, the policy's own."""
        state = self.state
        loss, score = fit_idm(self.policy, state.idm_optimizer, data, held_out, state.rng, own_held_out)
        self.stats.update({"idm_loss": loss, self.idm_metric: score})

    # ------------------------------------------------------------ checkpoints

    def save(self, directory: Path) -> None:
        """The training state and the cycle records beside a checkpoint."""
        if self.state is None:
            return
        saved = {**self.state.saved(self.policy.state_dict()), "averaged_weights": self.policy.averaged}
        torch.save(saved, directory / TRAINING_STATE_FILE)
        (directory / CYCLES_FILE).write_text("".join(json.dumps(c) + "\n" for c in self.state.cycles))
