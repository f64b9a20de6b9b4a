"""Fitting the arm model (``joint_idm.JointIDM``) inside a supervised ``lerobot-train`` run: its lag when the policy
is built, its linear parts in closed form on the first step, its network on every step on all but the last
``GATE_SHARE`` of each labelled episode, and its per-joint gate, whenever a checkpoint is saved, on those last
frames."""

from __future__ import annotations

import logging

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import nn

from lerobot_iupe.data.episodes import column_array
from lerobot_iupe.data.readers import ExpertFrames
from lerobot_iupe.policy.joint_idm import GATE_SHARE, best_copy_lag, gate_weights, max_lag
from lerobot_iupe.policy.train_run import training_episodes

log = logging.getLogger("lerobot_iupe")


def labelled_rows(episodes: np.ndarray) -> np.ndarray:
    """The rows (of a dataset whose rows belong to ``episodes``) that this run trains on: lerobot-train's
    ``--dataset.episodes``, all by default."""
    chosen = training_episodes()
    if chosen is None:
        return np.arange(len(episodes))
    return np.flatnonzero(np.isin(episodes, np.asarray(chosen)))


def lag_of_dataset(dataset_meta, columns: list[int]) -> int:
    """The lag at which the labelled episodes' actions best match their future joint states (``best_copy_lag``),
    read before the policy is built: it sets the IDM's window."""
    hf = LeRobotDataset(dataset_meta.repo_id, root=dataset_meta.root, video_backend="pyav").hf_dataset
    episodes = column_array(hf, "episode_index").reshape(-1)
    rows = labelled_rows(episodes)
    states = column_array(hf, OBS_STATE).astype(np.float64).reshape(len(hf), -1)[rows]
    actions = column_array(hf, ACTION).astype(np.float64).reshape(len(hf), -1)[rows]
    return best_copy_lag(states, actions, episodes[rows], columns, max_lag(dataset_meta.fps))


def gate_rows(expert: ExpertFrames, rows: np.ndarray) -> np.ndarray:
    """Which of ``rows`` (a boolean per row) lie in the last ``GATE_SHARE`` of their episode, on which the network
    is judged and never trained (none in an episode of under 5 frames)."""
    first, last = expert.first_row[rows], expert.last_row[rows]
    length = last - first + 1
    held = np.floor(length * GATE_SHARE).astype(np.int64)
    return (length >= 5) & (rows > last - held)


class JointFit:
    """The arm model's fit on one run's expert frames (``resume``: lerobot-train --resume=true, which keeps the
    saved linear parts)."""

    def __init__(self, policy: nn.Module, expert: ExpertFrames, resume: bool):
        self.policy, self.expert = policy, expert
        rows = labelled_rows(expert.episodes)
        rows = rows[expert.first_row[rows] != expert.last_row[rows]]  # a one-frame episode has no window
        held = gate_rows(expert, rows)
        self.train_rows, self.gate_rows = rows[~held], rows[held]
        self.is_gate_row = np.zeros(len(expert.episodes), dtype=bool)
        self.is_gate_row[self.gate_rows] = True
        encoder = policy.idm_encoder
        if not (resume and bool(encoder.fitted)):  # --resume=true goes on with its fit; a new run fits its own data
            windows = self.windows(rows).cpu().numpy()
            actions = expert.actions[torch.as_tensor(rows, device=expert.actions.device)].cpu().numpy()
            alphas = encoder.fit(windows, actions, expert.episodes[rows])
            log.info(
                f"IUPE arm IDM: lag {policy.config.idm_lag} frames, window {policy.config.idm_window}, ridge alphas "
                f"{alphas['ridge_alpha']} on {len(rows)} labelled frames ({len(self.gate_rows)} judge the network)"
            )

    def windows(self, rows: np.ndarray) -> torch.Tensor:
        return self.expert.vector_windows(OBS_STATE, rows, self.policy.config.idm_window)

    def training_rows(self, rows: np.ndarray) -> np.ndarray:
        """The batch's rows the network trains on (the gate's rows left out)."""
        return rows[~self.is_gate_row[rows]]

    @torch.no_grad()
    def update_gate(self) -> None:
        """Each joint keeps the share of the network's correction that helps on the gate's rows (0 without them)."""
        policy, encoder = self.policy, self.policy.idm_encoder
        if not len(self.gate_rows):
            encoder.gate.zero_()
            return
        was_training = policy.training
        policy.eval()
        window = self.windows(self.gate_rows)
        output = policy.joint_idm_output(window, gated=False)[:, : policy.config.action_dim]
        prior = policy.idm_head._scale(encoder.prior(window.float()))
        actions = self.expert.actions[torch.as_tensor(self.gate_rows, device=self.expert.actions.device)]
        target = policy.idm_head._scale(actions)
        gate = gate_weights((target - prior).cpu().numpy(), (output - prior).cpu().numpy())
        encoder.gate.copy_(torch.as_tensor(gate, dtype=torch.float32))
        policy.train(was_training)
