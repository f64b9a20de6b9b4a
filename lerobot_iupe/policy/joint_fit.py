"""Fitting the linear-first IDM (``joint_idm.JointIDM``) inside a supervised ``lerobot-train`` run: each joint's
source column and lag when the policy is built, its linear parts in closed form on the first step, its network on
every step on all but the last ``GATE_SHARE`` of each labelled episode, and its per-joint gate, whenever a checkpoint
is saved, on those last frames."""

from __future__ import annotations

import logging

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import nn

from lerobot_iupe.data.episodes import column_array
from lerobot_iupe.data.readers import ExpertFrames
from lerobot_iupe.policy.action_sources import (
    CAMERA,
    action_sources,
    idle_dimensions,
    is_rate_name,
    max_lag,
    named_sources,
    stem_sources,
)
from lerobot_iupe.policy.action_space import feature_names
from lerobot_iupe.policy.camera_reference import reference_rows
from lerobot_iupe.policy.joint_idm import GATE_SHARE, gate_weights
from lerobot_iupe.policy.train_run import training_episodes

log = logging.getLogger("lerobot_iupe")
# Rows whose camera frames are read at once (thumbnails, the gate's camera network): bounded memory at any dataset size.
REFERENCE_CHUNK = 64


def labelled_rows(episodes: np.ndarray) -> np.ndarray:
    """The rows (of a dataset whose rows belong to ``episodes``) that this run trains on: lerobot-train's
    ``--dataset.episodes``, all by default."""
    chosen = training_episodes()
    if chosen is None:
        return np.arange(len(episodes))
    return np.flatnonzero(np.isin(episodes, np.asarray(chosen)))


def named_columns(dataset_meta) -> list[int | None]:
    """For each action dimension, the ``observation.state`` column of the same name, or None (all None when the
    action's values have no names)."""
    features = dataset_meta.features
    named = named_sources(feature_names(features.get(ACTION)), feature_names(features.get(OBS_STATE)))
    size = int(np.prod(features.get(ACTION, {}).get("shape", (0,))))
    return named if len(named) == size else [None] * size


def named_joints(dataset_meta, columns: list[int]) -> list[bool]:
    """Whether each action dimension's source column is the state of its own name."""
    named = named_columns(dataset_meta)
    if len(named) != len(columns):
        return [False] * len(columns)
    return [n == c for n, c in zip(named, columns, strict=True)]


def sources_of_dataset(
    dataset_meta, named: list[int | None], lag: int | None = None, lowest: int = 0, cameras: bool = False
) -> tuple[list[int], list[int], list[str]] | None:
    """Each action dimension's source column, lag and kind, from the labelled episodes (``joint_idm.action_sources``;
    ``lag``: every dimension's lag, as --policy.idm_lag asks; ``lowest``: the earliest difference; ``cameras``: a
    dimension no column follows may be read off them), read before the policy is built: they set the IDM's window.
    None where the actions follow no state column."""
    hf = LeRobotDataset(dataset_meta.repo_id, root=dataset_meta.root, video_backend="pyav").hf_dataset
    episodes = column_array(hf, "episode_index").reshape(-1)
    rows = labelled_rows(episodes)
    states = column_array(hf, OBS_STATE).astype(np.float64).reshape(len(hf), -1)[rows]
    actions = column_array(hf, ACTION).astype(np.float64).reshape(len(hf), -1)[rows]
    longest = max_lag(dataset_meta.fps) if lag is None else lag
    features = dataset_meta.features
    action_names = feature_names(features.get(ACTION)) or []
    stems = stem_sources(action_names, feature_names(features.get(OBS_STATE)))
    rate_names = [is_rate_name(name) for name in action_names]
    if len(stems) != len(named):
        stems, rate_names = None, None
    sources = action_sources(states, actions, episodes[rows], named, longest, stems, rate_names, lowest, cameras)
    if sources is None or lag is None:
        return sources
    return sources[0], [lag] * len(sources[0]), sources[2]


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
        config = policy.config
        self.camera_parts = [i for i, key in enumerate(config.observation_keys) if key in config.camera_keys]
        rows = labelled_rows(expert.episodes)
        rows = rows[expert.first_row[rows] != expert.last_row[rows]]  # a one-frame episode has no window
        held = gate_rows(expert, rows)
        self.train_rows, self.gate_rows = rows[~held], rows[held]
        self.is_gate_row = np.zeros(len(expert.episodes), dtype=bool)
        self.is_gate_row[self.gate_rows] = True
        encoder = policy.idm_encoder
        actions = expert.actions[torch.as_tensor(rows, device=expert.actions.device)].cpu().numpy()
        self.idle = idle_dimensions(actions)  # these keep the bare copy: no network either
        if not (resume and bool(encoder.fitted)):  # --resume=true goes on with its fit; a new run fits its own data
            windows = self.windows(rows).cpu().numpy()
            named = named_joints(policy.dataset_meta, policy.config.joint_state_columns)
            fit = encoder.fit(windows, actions, expert.episodes[rows], named)
            kinds = policy.config.source_kinds
            if policy.config.camera_dims:
                self.fit_camera_reference(rows)
            log.info(
                f"IUPE linear-first IDM: sources {kinds}, lags {policy.config.idm_joint_lags} frames, window "
                f"{policy.config.idm_window[0]} … {policy.config.idm_window[-1]}, fits {fit['fit']}, ridge alphas "
                f"{fit['ridge_alpha']} on {len(rows)} labelled frames ({len(self.gate_rows)} judge the network)"
            )

    def windows(self, rows: np.ndarray) -> torch.Tensor:
        """The model's windows (B, F, D) of ``rows``: its vector keys joined, observation.state first."""
        config = self.policy.config
        parts = [self.expert.vector_windows(key, rows, config.idm_window) for key in config.idm_keys]
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def camera(self, rows: np.ndarray) -> torch.Tensor | None:
        """The camera network's frames of ``rows`` (None where no dimension reads a camera)."""
        config = self.policy.config
        if not config.camera_dims:
            return None
        return self.expert.part_windows(rows, config.camera_offsets, self.camera_parts)

    @torch.no_grad()
    def fit_camera_reference(self, rows: np.ndarray) -> None:
        """The camera dimensions' thumbnail ridge, on (at most ``MAX_REFERENCE_ROWS`` of) the labelled rows."""
        rows = reference_rows(rows)
        reference = self.policy.idm_camera.reference
        chunks = [rows[i : i + REFERENCE_CHUNK] for i in range(0, len(rows), REFERENCE_CHUNK)]
        thumbnails = np.concatenate([reference.thumbnails(self.camera(chunk)).cpu().numpy() for chunk in chunks])
        dims = self.policy.config.camera_dims
        actions = self.expert.actions[torch.as_tensor(rows, device=self.expert.actions.device)][:, dims]
        reference.fit(thumbnails, actions.cpu().numpy(), self.expert.episodes[rows])

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
        # In chunks: a camera dimension's network on every gate row's frames at once held gigabytes at 640×480.
        step = REFERENCE_CHUNK if policy.config.camera_dims else len(self.gate_rows)
        output = torch.cat([
            policy.joint_idm_output(window[i : i + step], gated=False, camera=self.camera(self.gate_rows[i : i + step]))
            for i in range(0, len(self.gate_rows), step)
        ])[:, : policy.config.action_dim]  # fmt: skip
        prior = policy.idm_head._scale(encoder.prior(window.float()))
        actions = self.expert.actions[torch.as_tensor(self.gate_rows, device=self.expert.actions.device)]
        target = policy.idm_head._scale(actions)
        gate = gate_weights((target - prior).cpu().numpy(), (output - prior).cpu().numpy())
        gate[self.idle & (np.asarray(policy.config.source_kinds) != CAMERA)] = 0.0  # idle: the bare copy
        encoder.gate.copy_(torch.as_tensor(gate, dtype=torch.float32))
        policy.train(was_training)
