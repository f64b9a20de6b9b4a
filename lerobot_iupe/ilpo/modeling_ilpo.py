"""ILPO policy: the latent policy network (LPN) and the action remapping network (ARN) in one LeRobot checkpoint.
This module is LeRobot's API; the online remapping phase is ``remapping.py``, the networks ``latent_model.py``."""

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import Tensor

from lerobot_iupe.ilpo.configuration_ilpo import ILPOConfig
from lerobot_iupe.ilpo.latent_model import (
    ActionRemappingNetwork,
    LatentPolicyNetwork,
    best_latent,
    expected_state_loss,
    min_latent_loss,
)
from lerobot_iupe.ilpo.remapping import ILPOTrainer
from lerobot_iupe.policy.threads import acting_threads


class ILPOPolicy(PreTrainedPolicy):
    config_class = ILPOConfig
    name = "ilpo"

    def __init__(self, config: ILPOConfig, dataset_stats: dict | None = None, dataset_meta=None, **kwargs):
        super().__init__(config)
        config.validate_features()
        config.resolve_dataset(dataset_meta)
        self.config = config
        self.layout = config.layout
        self.lpn = LatentPolicyNetwork(config)
        self.arn = ActionRemappingNetwork(config)
        visual = torch.zeros(self.layout.size, dtype=torch.bool)
        for i, is_camera in enumerate(self.layout.visual):
            visual[self.layout.columns(i)] = is_camera
        self.register_buffer("visual_columns", visual, persistent=False)
        # --policy.normalize: vector values by the dataset's stats, differences by their std over the expert's
        # pairs (set when training starts); saved, so that acting reads states as training did.
        self.register_buffer("state_mean", torch.zeros(self.layout.size))
        self.register_buffer("state_std", torch.ones(self.layout.size))
        self.register_buffer("difference_std", torch.ones(self.layout.size))
        if config.normalize and dataset_stats:
            for i, key in enumerate(config.observation_keys):
                if not self.layout.visual[i] and key in dataset_stats:
                    columns = self.layout.columns(i)
                    self.state_mean[columns] = torch.as_tensor(dataset_stats[key]["mean"]).float().reshape(-1)
                    self.state_std[columns] = torch.as_tensor(dataset_stats[key]["std"]).float().reshape(-1)
            self.state_std.clamp_(min=1e-6)
        self.dataset_meta = dataset_meta
        # lerobot-train seeds torch with its --seed just before building the policy: that seed drives ILPO's own
        # streams unless --policy.seed is given.
        seed = config.seed if config.seed is not None else torch.initial_seed() % 2**62
        self.trainer = ILPOTrainer(self, dataset_meta, seed) if dataset_meta is not None else None

    # ------------------------------------------------------------ frames and the two networks

    def flat(self, frames: Tensor) -> Tensor:
        """Joined frames (B, …) as the networks read them: (B, size) floats, a lone camera scaled to [0, 1]."""
        frames = frames.reshape(len(frames), -1)
        if frames.dtype == torch.uint8:
            return frames.float() / 255.0
        if self.config.normalize:
            return (frames.float() - self.state_mean) / self.state_std
        return frames.float()

    def difference(self, frames: Tensor, next_frames: Tensor) -> Tensor:
        """What the generator predicts of a transition: s_{t+1} − s_t (``normalize``: over its std per value)."""
        delta = next_frames - frames
        return delta / self.difference_std if self.config.normalize else delta

    @torch.no_grad()
    def fit_difference_scale(self, frames: Tensor, next_frames: Tensor) -> None:
        """``normalize``: each value's std of s_{t+1} − s_t over these pairs, in normalised state units."""
        delta = self.flat(next_frames) - self.flat(frames)
        self.difference_std.copy_(delta.std(dim=0).clamp_min(1e-6))

    def predicted_next(self, frames: Tensor) -> Tensor:
        """ŝ^z = s + G(s, z) for every z (B, Z, size); camera values kept in [0, 1]."""
        _, predicted = self.lpn(frames)
        if self.config.normalize:
            predicted = predicted * self.difference_std
        candidates = frames.unsqueeze(1) + predicted
        if self.layout.fused or self.config.is_image:
            candidates = torch.where(self.visual_columns, candidates.clamp(0.0, 1.0), candidates)
        return candidates

    @torch.no_grad()
    def explaining_latents(self, frames: Tensor, next_frames: Tensor) -> Tensor:
        """z* of each transition: the latent action whose predicted next state is nearest the real one — in state
        space for vectors, in E_p's embedding for cameras (as the authors compare images)."""
        if not self.config.is_image and self.config.normalize:  # nearest in the scaled differences
            return best_latent(self.difference(frames, next_frames), self.lpn(frames)[1])
        candidates = self.predicted_next(frames)
        if not self.config.is_image:
            return best_latent(next_frames, candidates)
        batch, n_latent, size = candidates.shape
        embedded = self.lpn.embed(candidates.reshape(batch * n_latent, size)).reshape(batch, n_latent, -1)
        return best_latent(self.lpn.embed(next_frames), embedded)

    def act(self, frames: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        """Actions (B, …) for flat frames: z = argmax π(z|s) (a draw from π when ``explore``), then the ARN's action
        for (s, z): its mode, or a draw."""
        logits, _ = self.lpn(frames)
        if explore:
            z = torch.multinomial(torch.softmax(logits, -1), 1, generator=generator)[:, 0]
        else:
            z = logits.argmax(-1)
        return self.arn.head.choose(self.arn(frames, z), explore, generator)

    def lpn_losses(self, frames: Tensor, next_frames: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """L_min, L_exp, the winning z per sample and π (B, Z) on a batch of expert pairs."""
        logits, predicted = self.lpn(frames)
        delta = self.difference(frames, next_frames)
        l_min, winners = min_latent_loss(delta, predicted)
        probabilities = torch.softmax(logits, dim=-1)
        return l_min, expected_state_loss(delta, predicted, probabilities), winners, probabilities

    # ------------------------------------------------------------ what PolicyRollouts plays

    @property
    def device_of_weights(self) -> torch.device:
        return self.lpn.policy.weight.device

    def push_history(self, history: Tensor | None, observation: Tensor) -> Tensor:
        """ILPO reads the current observation only: a history of one."""
        return observation.unsqueeze(1)

    def rollout_actions(self, history: Tensor, explore: bool, generator: torch.Generator | None = None) -> Tensor:
        return self.act(self.flat(history[:, -1]), explore, generator)

    @contextmanager
    def averaged_weights(self) -> Iterator[None]:
        """ILPO keeps no weight average: the block runs on the weights as they are."""
        yield

    # ------------------------------------------------------------ LeRobot API

    def get_optim_params(self):
        """The LPN's parameters (LeRobot's optimizer trains them offline); the ARN has its own optimizer online."""
        return list(self.lpn.parameters())

    def reset(self) -> None:
        """ILPO keeps no state between steps."""

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        return self.select_action(batch).unsqueeze(1)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs) -> Tensor:
        """argmax_z π(z|s), then the ARN's most likely action for (s, z) (``eval_mode="sample"``: draws of both),
        (B, action_dim) as LeRobot's env loop wants it."""
        with acting_threads(self.config.threads):
            frames = self.flat(self.layout.join([batch[k] for k in self.config.observation_keys]))
            actions = self.act(frames, self.config.eval_mode == "sample")
            return self.arn.head.as_float_action(actions)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """One LPN step on the batch's expert pairs (s_t, s_{t+1}), read from the in-memory expert data by the
        batch's frame ``index``: L_min + L_exp, weight 1 each."""
        if "index" not in batch:
            raise ValueError("ILPO's forward needs the batch's frame 'index' (as LeRobot's dataset loader gives it)")
        if self.trainer is None:
            raise RuntimeError("ILPO training needs the expert dataset's metadata (make_policy(ds_meta=…))")
        expert = self.trainer.expert_frames()
        state, next_state = expert.pairs(expert.rows(batch["index"]))
        l_min, l_exp, winners, probabilities = self.lpn_losses(self.flat(state), self.flat(next_state))
        self.trainer.count_latents(winners, probabilities)
        loss = l_min + l_exp
        return loss, {"lpn_min_loss": float(l_min.detach()), "lpn_expected_loss": float(l_exp.detach())}

    def update(self) -> None:
        if self.trainer is not None:
            self.trainer.step_done()

    def remap(self) -> dict:
        """Run the online remapping phase now (lerobot-train runs it after its last step); its summary."""
        if self.trainer is None:
            raise RuntimeError("ILPO's remapping needs the expert dataset's metadata (make_policy(ds_meta=…))")
        return self.trainer.remap()

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Save both networks (the selected ARN when remapping selected one) and beside them ILPO's state."""
        if state_dict is None and self.trainer is not None and self.trainer.selected_arn is not None:
            state_dict = {**self.state_dict(), **self.trainer.selected_arn}
        super()._save_pretrained(save_directory, state_dict)
        if self.trainer is not None:
            self.trainer.save(Path(save_directory))
