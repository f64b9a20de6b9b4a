"""The linear part of every other IDM of continuous actions (the cycle's, and a supervised one that is not the arm
model): a ridge regression from the vector part of the IDM's window to a_t, solved in closed form, under the network,
which learns what it leaves. Velocities, end-effector deltas and thrust are linear in the differences of the state's
frames, which a ridge finds at once and a network trained for a few epochs on play does not (benchmarks/cycle_play.md:
Meta-World's cycle IDM below the ridge on reach, drawer-open and button-press-topdown). Zero until fitted, so a
checkpoint saved before it existed labels as it did."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from lerobot_iupe.data.readers import ExpertFrames
from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.policy.joint_fit import labelled_rows
from lerobot_iupe.policy.joint_idm import MAX_FOLDS, RIDGE_ALPHAS, fit_ridge, gate_weights

# The cycle's strength per frame: fitted on play and scored on the expert, a strength chosen on held-out play labelled
# Meta-World push's expert worse (hand x / y / z R² 0.58 / 0.67 / 0.01 against 0.90 / 0.79 / 0.32 at this one;
# benchmarks/measure/cycle_context.py).
SHIFT_STRENGTH = 1e-3


def contiguous_folds(count: int) -> np.ndarray:
    """A fold number per row: ``MAX_FOLDS`` contiguous blocks of rows in their order (an episode's neighbouring
    frames, nearly equal, stay in one fold)."""
    return np.arange(count) * min(MAX_FOLDS, max(count, 1)) // max(count, 1)


class LinearPrior(nn.Module):
    """a_t ≈ flat(window[:, :, columns]) @ weight + bias, raw action units, for windows (B, F, values) of joined
    frames; ``columns``: the vector values the IDM reads. Binary dimensions (a gripper's logit) get none."""

    def __init__(self, frames: int, columns: list[int], action_dim: int):
        super().__init__()
        self.register_buffer("columns", torch.as_tensor(columns, dtype=torch.long), persistent=False)
        self.register_buffer("weight", torch.zeros(frames * len(columns), action_dim))
        self.register_buffer("bias", torch.zeros(action_dim))
        self.register_buffer("fitted", torch.zeros((), dtype=torch.bool))
        # The share of the network's correction kept when labelling, per dimension (``judge_gate``).
        self.register_buffer("gate", torch.ones(action_dim))
        self.is_fitted = False  # ``fitted`` as a Python bool: reading the buffer waits for the GPU on every pass

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self.is_fitted = bool(self.fitted)

    def features(self, windows: np.ndarray | Tensor, selected: bool = False) -> np.ndarray | Tensor:
        """[s_t, s_j − s_t for every other frame j] (N, F × columns), flattened, of the vector values of raw windows
        (N, F, values) at offsets -k … k+1 (``selected``: windows of ``columns`` alone): as the network reads them.
        With the frames themselves, standardised, a ridge shrinks the small differences that velocities are away."""
        columns = self.columns.cpu().numpy() if isinstance(windows, np.ndarray) else self.columns.to(windows.device)
        values = windows if selected else windows[:, :, columns]
        k = (values.shape[1] - 2) // 2
        start = values[:, k : k + 1]
        others = [values[:, :k] - start, values[:, k + 1 :] - start]
        joined = (
            np.concatenate([start, *others], axis=1)
            if isinstance(values, np.ndarray)
            else torch.cat([start, *others], dim=1)
        )
        return joined.reshape(len(windows), joined.shape[1] * joined.shape[2])  # no -1: zero windows have a shape

    def forward(self, window: Tensor) -> Tensor:
        return self.features(window).float() @ self.weight + self.bias

    @torch.no_grad()
    def fit(self, features: np.ndarray, actions: np.ndarray, keep: np.ndarray, fixed: bool = False) -> None:
        """Fit on ``features`` (N, F × columns, as ``features`` gives them) and actions (N, A), each dimension's
        strength chosen on contiguous folds, or with ``fixed`` (the cycle's play, scored on an expert it never
        saw) ``SHIFT_STRENGTH`` · N; exact repeats (I^s draws copies of successful transitions) count once, so that a
        copy is never judged by itself. Dimensions outside ``keep`` stay at 0."""
        features = np.asarray(features, np.float64)
        actions = np.asarray(actions, np.float64).reshape(len(features), -1)
        if len(features) < 2 * MAX_FOLDS or not keep.any():
            return
        _, first = np.unique(np.concatenate([features, actions], axis=1), axis=0, return_index=True)
        rows = np.sort(first)
        features, actions = features[rows], actions[rows][:, keep]
        alphas = (SHIFT_STRENGTH * len(rows),) if fixed else RIDGE_ALPHAS
        weight, bias, _, _ = fit_ridge(features, actions, rows, alphas, folds=contiguous_folds(len(rows)))
        self.weight.zero_()
        self.bias.zero_()
        self.weight[:, torch.as_tensor(keep)] = torch.as_tensor(weight, dtype=torch.float32)
        self.bias[torch.as_tensor(keep)] = torch.as_tensor(bias, dtype=torch.float32)
        self.fitted.fill_(True)
        self.is_fitted = True


def expert_features(prior: LinearPrior, expert: ExpertFrames, offsets: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """What a supervised IDM's linear part is fitted on: the features (``LinearPrior.features``) and actions of this
    run's labelled frames. It reads the vector columns alone: windows of joined frames carry every camera value
    (4,096 of two 96×128 cameras were 4.8 GB, and 5,000 frames took 3.7 s to read from the frame cache for nothing)."""
    rows = labelled_rows(expert.episodes)
    values = expert.column_windows(rows, offsets, prior.columns.cpu().tolist())
    actions = expert.actions[torch.as_tensor(rows, device=expert.actions.device)].cpu().numpy()
    return prior.features(values, selected=True), actions


@torch.no_grad()
def judge_gate(policy: nn.Module, held_out: Transitions | None) -> None:
    """Per dimension, the share of the network's correction that helps on ``held_out`` (``gate_weights``): the
    policy's own rollout transitions, which the network did not train on; a binary dimension keeps all of it. With
    none (the first IDM, fitted on play alone) the share is 0 and the linear part labels alone: on Meta-World the
    network, fitted to play, labelled the expert below its linear part on 3 of 4 tasks even with its share judged on
    held-out play, or on the held-out play nearest each expert window (benchmarks/cycle_gate.md)."""
    prior, head, dims = policy.idm_prior, policy.idm_head, policy.config.action_dim
    prior.gate.fill_(1.0)  # the network's whole correction while it is judged
    if held_out is None or not len(held_out):
        prior.gate.copy_(head.binary.float())
        return
    was_training = policy.training
    policy.eval()
    corrections, residuals = [], []
    for start in range(0, len(held_out), 1024):
        part = held_out.take(np.arange(start, min(start + 1024, len(held_out))))
        window = torch.as_tensor(part.windows, device=prior.weight.device)
        shift = head._scale(prior(window))
        corrections.append((policy.idm_window_output(window)[:, :dims].float() - shift).cpu().numpy())
        residuals.append((head._scale(torch.as_tensor(part.actions, device=shift.device)) - shift).cpu().numpy())
    gate = gate_weights(np.concatenate(residuals), np.concatenate(corrections))
    gate[head.binary.cpu().numpy()] = 1.0
    prior.gate.copy_(torch.as_tensor(gate, dtype=torch.float32))
    policy.train(was_training)
