"""IUPE policy: an inverse dynamics model (IDM) P(a | s_t, s_{t+1}) and a policy model (PM) P(a | s_t) in one
LeRobot checkpoint. This module is LeRobot's API only; the algorithm that trains them inside ``lerobot-train``
is ``training.py``, the networks ``networks.py`` and ``heads.py``.

The checkpoint LeRobot saves holds the *selected* model (``algorithm.selects``) as its weights, and
beside them what the algorithm needs to go on exactly where it stopped (``training.TrainingState``). Training from
such a checkpoint with ``--resume=true`` continues from that state; ``--policy.path`` alone starts a new run
from its weights (``train_run``).
"""

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor, nn

from lerobot_iupe.policy.algorithm import frame_differences
from lerobot_iupe.policy.configuration_iupe import IDM_ONLY_CANNOT_ACT, IUPEConfig
from lerobot_iupe.policy.heads import make_action_head
from lerobot_iupe.policy.joint_idm import JointIDM
from lerobot_iupe.policy.linear_prior import LinearPrior, expert_features
from lerobot_iupe.policy.networks import CameraIDM, FusedEncoder, VectorEncoder, make_image_encoder
from lerobot_iupe.policy.threads import acting_threads
from lerobot_iupe.policy.training import IUPETrainer


class IUPEPolicy(PreTrainedPolicy):
    config_class = IUPEConfig
    name = "iupe"

    def __init__(self, config: IUPEConfig, dataset_stats: dict | None = None, dataset_meta=None, **kwargs):
        super().__init__(config)
        config.validate_features()
        config.resolve_dataset(dataset_meta)
        self.config = config
        # The keys are joined into one array per frame in observation_keys order (config.layout): vectors
        # concatenated, a single camera as it is, a camera with other keys packed flat and fused by FusedEncoder.
        layout, hidden = config.layout, config.hidden_dim
        frames, history = len(config.idm_window), config.n_obs_steps
        columns = layout.indices(i for i, key in enumerate(config.observation_keys) if key in config.idm_keys)
        self.idm_columns = None if len(columns) == layout.size else torch.as_tensor(columns)
        if config.joint_idm:  # actions read from the state (an arm's leader): the linear-first model
            if not config.idm_joint_lags or len(config.idm_joint_lags) != len(config.joint_state_columns):
                raise ValueError(
                    f"this checkpoint's linear-first IDM has joint_state_columns={config.joint_state_columns} but "
                    f"idm_joint_lags={config.idm_joint_lags}: it was trained by an earlier version of lerobot_iupe, "
                    "whose arm model this one cannot read; train it again (lerobot-train --policy.type=iupe "
                    "--policy.supervised=true …)"
                )
            self.idm_encoder = JointIDM(
                config.idm_window, config.idm_joint_lags, config.joint_state_columns, len(columns), config.hidden_dim,
                config.source_kinds,
            )  # fmt: skip
            if config.camera_dims:  # dimensions no state column follows: a camera network of their own
                cameras = [i for i, key in enumerate(config.observation_keys) if key in config.camera_keys]
                self.register_buffer("camera_columns", torch.as_tensor(layout.indices(cameras)), persistent=False)
                self.camera_span = layout.span(cameras)
                self.idm_camera = CameraIDM(config.layout_of(config.camera_keys), len(config.camera_dims), config)
            self.pm_encoder = (
                FusedEncoder(layout, history, config)
                if layout.fused
                else VectorEncoder(history * layout.size, config.token_dim, hidden, config.attention)
            )
        elif layout.fused:
            self.idm_encoder = FusedEncoder(config.layout_of(config.idm_keys), frames, config)
            self.pm_encoder = FusedEncoder(layout, history, config)
        elif config.is_image:
            channels = layout.shapes[0][0]
            encoder = lambda c: make_image_encoder(  # noqa: E731
                config.image_backbone, c, config.cnn_width, hidden, config.attention
            )
            self.idm_encoder, self.pm_encoder = encoder(frames * channels), encoder(history * channels)
        else:
            self.idm_encoder = VectorEncoder(frames * len(columns), config.token_dim, hidden, config.attention)
            self.pm_encoder = VectorEncoder(history * layout.size, config.token_dim, hidden, config.attention)
        self.idm_head = make_action_head(config.action_dim if config.joint_idm else hidden, config)
        if config.joint_idm:  # the head's mean passes each joint's correction on as it is, to start with
            self.idm_head.clipped = False
            with torch.no_grad():
                self.idm_head.weight[: config.action_dim] = torch.eye(config.action_dim)
                self.idm_head.bias.zero_()
        self.pm_head = make_action_head(hidden, config)
        prior_columns = [c for c in layout.indices(i for i, v in enumerate(layout.visual) if not v) if c in columns]
        self.idm_prior = (  # the linear part under a continuous IDM's network (linear_prior.py)
            LinearPrior(frames, prior_columns, config.action_dim)
            if config.idm_linear_part and config.is_continuous and not config.joint_idm and prior_columns
            else None
        )
        if self.idm_prior is not None:  # the network's mean starts at 0: the IDM starts at the linear part
            with torch.no_grad():
                self.idm_head.weight[: config.action_dim] = 0.0
                self.idm_head.bias[: config.action_dim] = 0.0
        # Per-value normalisation of a joined frame: vectors by the dataset's stats, fused cameras (already in
        # [0, 1]) left as they are; a lone camera is scaled in _prepare.
        state_dim = 1 if config.is_image and not layout.fused else layout.size
        self.register_buffer("state_mean", torch.zeros(state_dim))
        self.register_buffer("state_std", torch.ones(state_dim))
        if state_dim > 1 or not config.is_image:
            for i, key in enumerate(config.observation_keys):
                if layout.visual[i] or not dataset_stats or key not in dataset_stats:
                    continue
                mean, std = (np.asarray(dataset_stats[key][n], dtype=np.float32).reshape(-1) for n in ("mean", "std"))
                self.state_mean[layout.columns(i)] = torch.as_tensor(mean)
                self.state_std[layout.columns(i)] = torch.as_tensor(std).clamp_min(1e-3)
        self.layout = layout  # read on every select_action and rollout step
        vector_columns = layout.indices(i for i, visual in enumerate(layout.visual) if not visual)
        self.register_buffer("vector_columns", torch.as_tensor(vector_columns, dtype=torch.long), persistent=False)
        self.dataset_meta = dataset_meta
        self._history: Tensor | None = None  # select_action's last n_obs_steps observations (B, n, …)
        self.averaged: dict[str, Tensor] | None = None  # the policy model's weight average (config.ema_decay)
        # lerobot-train seeds torch with its --seed just before building the policy: that seed drives IUPE's own
        # streams unless --policy.seed is given.
        seed = config.seed if config.seed is not None else torch.initial_seed() % 2**62
        # Training on a dataset (lerobot-train); it opens nothing until the first step.
        self.trainer = IUPETrainer(self, dataset_meta, seed) if dataset_meta is not None else None

    # ------------------------------------------------------------ the two models

    def _prepare(self, obs: Tensor) -> Tensor:
        """Frames (…, frame) as the encoders take them: a lone camera in [0, 1], vectors normalised by the dataset's
        stats; a fused frame's camera values, already in [0, 1], are left as they are (their stats are 0 and 1)."""
        if self.config.is_image and not self.layout.fused:
            return obs.float() / 255.0 if obs.dtype == torch.uint8 else obs.float()
        if not self.layout.fused:
            return (obs.float() - self.state_mean) / self.state_std
        columns = self.vector_columns.to(obs.device)
        prepared = obs.float().clone()
        prepared[..., columns] = (prepared[..., columns] - self.state_mean[columns]) / self.state_std[columns]
        return prepared

    def idm_output(self, state: Tensor, next_state: Tensor) -> Tensor:
        """The IDM head's distribution parameters (logits) for a → (s_t, s_{t+1}) (an IDM without context)."""
        if self.config.idm_context:
            raise ValueError(
                f"this IDM reads {len(self.config.idm_window)} frames (idm_context={self.config.idm_context}); "
                "use idm_window_output"
            )
        return self.idm_window_output(torch.stack([state, next_state], dim=1))

    def idm_window_output(self, window: Tensor) -> Tensor:
        """The IDM head's distribution parameters for a_t → frames (B, 2k+2, …) at offsets -k … k+1 of t."""
        # Input [s_t, s_j - s_t for every other frame j]: with frame differences an image IDM learns in far fewer
        # steps than from separately encoded frames (0.995 vs 0.71 accuracy on expert moves in a reference
        # measurement). For k = 0 this is [s_t, s_{t+1} - s_t].
        k = self.config.idm_context or 0
        if self.config.joint_idm:
            columns = None if self.idm_columns is None else self.idm_columns.to(window.device)
            state = window if columns is None else window[:, :, columns]
            return self.joint_idm_output(state, camera=self.camera_frames(window) if self.config.camera_dims else None)
        if self.layout.fused and self.idm_columns is None:
            output = self.idm_head(self.idm_encoder.encode_parts(*self._fused_difference_parts(window, k)))
            return self.with_prior(output, window)
        frames = self._prepare(window)
        if self.idm_columns is not None:  # --policy.idm_observation_keys: the IDM reads some keys only
            frames = frames[:, :, self.idm_columns.to(frames.device)]
        s = frames[:, k : k + 1]
        differences = torch.cat([frames[:, :k], frames[:, k + 1 :]], dim=1) - s
        return self.with_prior(
            self.idm_head(self.idm_encoder(torch.cat([s, differences], dim=1).flatten(1, 2))), window
        )

    def with_prior(self, output: Tensor, window: Tensor) -> Tensor:
        """The network's ``output`` with the fitted linear part of raw ``window`` added to its mean (scaled units;
        not on a binary dimension, whose mean is a logit), the network's share gated when not training."""
        prior = self.idm_prior
        if prior is None or not prior.is_fitted:
            return output
        head, dims = self.idm_head, self.config.action_dim
        shift = torch.where(head.binary, 0.0, head._scale(prior(window))).to(output.dtype)
        gate = 1.0 if self.training else prior.gate.to(output.dtype)
        return torch.cat([shift + gate * output[:, :dims], output[:, dims:]], dim=-1)

    def fit_prior(self, features, actions, fixed: bool) -> None:
        """Fit the linear part on ``features`` (``LinearPrior.features`` of raw windows) and their actions."""
        if self.idm_prior is not None:
            self.idm_prior.fit(features, actions, ~self.idm_head.binary.cpu().numpy(), fixed)

    @property
    def labelling_keys(self) -> list[str]:
        """The observation keys relabelling reads: the linear-first model's joint states alone (its cameras are never
        decoded) unless a dimension is read off the cameras, else every key of the policy (``idm_window_output``
        takes them joined)."""
        if self.config.joint_idm and not self.config.camera_dims:
            return self.config.idm_keys
        return self.config.observation_keys

    def labelling_output(self, window: Tensor) -> Tensor:
        """The IDM's distribution parameters for windows (B, F, …) of ``labelling_keys``, joined."""
        if self.config.joint_idm and not self.config.camera_dims:
            return self.joint_idm_output(window)
        return self.idm_window_output(window)

    def camera_frames(self, window: Tensor) -> Tensor:
        """The camera network's frames (B, len(camera_offsets), camera values) out of joined frames of every
        observation key at the IDM's window offsets."""
        frames = [self.config.idm_window.index(offset) for offset in self.config.camera_offsets]
        cameras = window[:, :, self.camera_span or self.camera_columns.to(window.device)]  # a view where adjacent
        run = frames[-1] - frames[0] == len(frames) - 1
        return cameras[:, frames[0] : frames[-1] + 1] if run else cameras[:, frames]

    def camera_reference(self, window: Tensor) -> Tensor:
        """The camera dimensions' thumbnail ridge (``camera_reference.py``) on joined frames at the IDM's offsets."""
        return self.idm_camera.reference(self.camera_frames(window))

    def joint_idm_output(self, window: Tensor, gated: bool | None = None, camera: Tensor | None = None) -> Tensor:
        """The linear-first model's distribution parameters for a_t → joint-state windows (B, F, D), raw units: the
        head's mean is the linear prior (copy plus ridge) plus the network's correction (for a camera dimension,
        also the camera network's on ``camera``, frames at ``camera_offsets``), times the per-dimension gate when
        ``gated`` (default: in eval mode; training fits the networks ungated)."""
        encoder, head = self.idm_encoder, self.idm_head
        window = window.float()
        output = head(encoder(window))
        if self.config.camera_dims:  # added after the head, whose weights mix dimensions: the others never read it
            if camera is None:
                raise ValueError(f"action dimensions {self.config.camera_dims} are read off the cameras: pass camera=")
            dims = torch.as_tensor(self.config.camera_dims, device=output.device)
            output = output.index_add(1, dims, self.idm_camera(camera).to(output.dtype))
        correction, log_std = output.split(self.config.action_dim, dim=-1)
        if self.training if gated is None else not gated:
            gate = 1.0
        else:
            gate = encoder.gate
        return torch.cat([head._scale(encoder.prior(window)) + gate * correction, log_std], dim=-1)

    def _fused_difference_parts(self, window: Tensor, k: int) -> tuple[list[Tensor], Tensor | None]:
        """[s_t, s_j - s_t …] of fused frames (B, F, size), written once per key into what ``encode_parts`` reads:
        cameras (B, F · C, H, W), vectors (B, F · D) (differences divided by the std; the means cancel). The general
        path's values without its copies of whole frames (40% of an image IDM's labelling at 96×128)."""
        window, layout, encoder = window.float(), self.layout, self.idm_encoder
        b = len(window)
        cameras = [frame_differences(window[:, :, layout.columns(i)], k).view(b, -1, *layout.shapes[i][1:])
                   for i in encoder.cameras]  # fmt: skip
        if encoder.vector_encoder is None:
            return cameras, None
        columns = self.vector_columns.to(window.device)
        vectors = frame_differences(window[:, :, columns], k)
        vectors[:, 0] = (vectors[:, 0] - self.state_mean[columns]) / self.state_std[columns]
        vectors[:, 1:] /= self.state_std[columns]
        return cameras, vectors.flatten(1)

    def pm_output(self, state: Tensor) -> Tensor:
        """The policy head's distribution parameters (logits) for a → s_t (a policy of the current state only)."""
        if self.config.n_obs_steps > 1:
            raise ValueError(
                f"this policy reads {self.config.n_obs_steps} observations (n_obs_steps); use pm_history_output"
            )
        return self.pm_history_output(state.unsqueeze(1))

    def pm_history_output(self, history: Tensor) -> Tensor:
        """The policy head's distribution parameters for a_t → the last observations (B, n_obs_steps, …), oldest
        first, concatenated (channels for images)."""
        return self.pm_head(self.pm_encoder(torch.cat(list(self._prepare(history).unbind(1)), dim=1)))

    def rollout_actions(self, history: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        """The policy model's actions on the last observations (B, n_obs_steps, …): draws or modes."""
        return self.pm_head.choose(self.pm_history_output(history), explore, generator)

    def push_history(self, history: Tensor | None, observation: Tensor) -> Tensor:
        """``history`` (B, n, …) moved on by one ``observation`` (B, …); a new episode (None, or another batch
        size) starts as n copies of its first observation."""
        if history is None or history.shape[0] != observation.shape[0]:
            return observation.unsqueeze(1).repeat_interleave(self.config.n_obs_steps, dim=1)
        return torch.cat([history[:, 1:], observation.unsqueeze(1)], dim=1)

    def observation(self, batch: dict[str, Tensor]) -> Tensor:
        """The policy's input from a LeRobot batch: its observation keys joined in the recorded order."""
        return self.layout.join([batch[k] for k in self.config.observation_keys])

    def idm_parameters(self) -> list[nn.Parameter]:
        camera = list(self.idm_camera.parameters()) if self.config.camera_dims else []
        return list(self.idm_encoder.parameters()) + list(self.idm_head.parameters()) + camera

    def update_average(self) -> None:
        """After an optimizer step: move the policy model's weight average towards its weights (``ema_decay``);
        the first step starts it at them."""
        if not self.config.ema_decay:
            return
        weights = {n: p.detach() for n, p in self.named_parameters() if n.startswith("pm_")}
        if self.averaged is None:
            self.averaged = {n: w.clone() for n, w in weights.items()}
            return
        for name, average in self.averaged.items():
            average.lerp_(weights[name], 1.0 - self.config.ema_decay)

    @contextmanager
    def averaged_weights(self) -> Iterator[None]:
        """Inside the block the policy model holds its weight average (none yet: its weights); after it, the weights
        the optimizer trains again."""
        if self.averaged is None:
            yield
            return
        parameters = dict(self.named_parameters())
        trained = {n: parameters[n].detach().clone() for n in self.averaged}
        with torch.no_grad():
            for name, average in self.averaged.items():
                parameters[name].copy_(average)
        try:
            yield
        finally:
            with torch.no_grad():
                for name, weights in trained.items():
                    parameters[name].copy_(weights)

    @property
    def device_of_weights(self) -> torch.device:
        return self.pm_head.weight.device

    @property
    def cycles(self) -> list[dict]:
        """One record per finished cycle (``iupe_cycles.jsonl``)."""
        return self.trainer.cycles if self.trainer else []

    # ------------------------------------------------------------ LeRobot API

    def get_optim_params(self):
        """The policy model's parameters; supervised, the IDM's too (both learn from the true actions); the IDM's
        alone with ``idm_only``."""
        pm = [] if self.config.idm_only else list(self.pm_encoder.parameters()) + list(self.pm_head.parameters())
        return pm + self.idm_parameters() if self.config.supervised else pm

    def reset(self) -> None:
        """A new episode: forget the observation history (LeRobot's env loop calls this before each rollout)."""
        self._history = None

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.select_action(batch).unsqueeze(1)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """The policy model's action as LeRobot's env loop wants it, (B, action_dim): the mode, or a draw with
        ``eval_mode="sample"`` (whatever the training switches). Training rollouts draw on their own."""
        if self.config.idm_only:
            raise ValueError(IDM_ONLY_CANNOT_ACT)
        with acting_threads(self.config.threads):
            self._history = self.push_history(self._history, self.observation(batch))
            output = self.pm_history_output(self._history)
            return self.pm_head.as_float_action(self.pm_head.choose(output, self.config.eval_mode == "sample"))

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """One PM step on the batch's frames: s_t and the IDM's window around it (s_{t+1}, or with idm_context k
        s_{t-k} … s_{t+1+k}) come from the in-memory expert data by the batch's frame ``index``; labels are the
        IDM's (or, with ``supervised``, the dataset's true actions)."""
        if "index" not in batch:
            raise ValueError("IUPE's forward needs the batch's frame 'index' (as LeRobot's dataset loader gives it)")
        if self.trainer is None:
            raise RuntimeError("IUPE training needs the expert dataset's metadata (make_policy(ds_meta=…))")
        expert = self.trainer.expert_frames()
        rows = expert.rows(batch["index"])
        if self.config.supervised:  # BC on the true actions (not with idm_only), and the IDM on the same ones
            labels = expert.actions[rows]
            if self.config.joint_idm:
                window, camera, idm_rows = self.trainer.joint_idm_batch(rows)
                idm_loss = self.idm_head.loss(self.joint_idm_output(window, camera=camera), expert.actions[idm_rows])
            else:
                if self.idm_prior is not None and not self.trainer.prior_ready:  # on the first step
                    self.trainer.prior_ready = True
                    if not (self.trainer.resume and self.idm_prior.is_fitted):
                        self.fit_prior(*expert_features(self.idm_prior, expert, self.config.idm_window), fixed=False)
                window = expert.windows(rows, self.config.idm_window)
                idm_loss = self.idm_head.loss(self.idm_window_output(window), labels)
            if self.config.idm_only:
                return idm_loss, {"idm_loss": float(idm_loss.detach())}
            pm_loss = self.pm_head.loss(self.pm_history_output(expert.windows(rows, self.config.obs_window)), labels)
            return pm_loss + idm_loss, {"pm_loss": float(pm_loss.detach()), "idm_loss": float(idm_loss.detach())}
        # first: on the first step it starts (or restores) the cycle
        labels, spread = self.trainer.labels(expert.transition_windows(rows, self.config.idm_window))
        loss = self.pm_head.loss(self.pm_history_output(expert.windows(rows, self.config.obs_window)), labels, spread)
        return loss, {"pm_loss": float(loss.detach()), **self.trainer.stats}

    def update(self) -> None:
        self.update_average()
        if self.trainer is None or (self.config.supervised and not self.config.separate_selection_episodes):
            return
        self.trainer.step_done()

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Save the model selected by rollout success (the current one before any rollout), and beside it the
        algorithm's state and its cycle records."""
        if self.trainer is not None and self.config.joint_idm:
            self.trainer.update_joint_gate()
        if state_dict is None and self.trainer is not None and self.trainer.selected_weights is not None:
            state_dict = self.trainer.selected_weights
            if self.config.supervised:  # the policy model is selected; the IDM, learning the true actions, is kept
                state_dict = {**state_dict, **{k: v for k, v in self.state_dict().items() if k.startswith("idm_")}}
        elif state_dict is None and self.averaged is not None:  # nothing selected: the latest weight average
            with self.averaged_weights():
                state_dict = {k: v.clone() for k, v in self.state_dict().items()}
        super()._save_pretrained(save_directory, state_dict)
        if self.trainer is not None:
            self.trainer.save(Path(save_directory))
