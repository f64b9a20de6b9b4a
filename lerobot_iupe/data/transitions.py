"""Aligned transitions (s_t, a_t, s_{t+1}): what the inverse dynamics model learns from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Transitions:
    """Aligned (s_t, a_t, s_{t+1}) of the same step; states are arrays or tensors with a leading N axis."""

    states: np.ndarray
    actions: np.ndarray
    next_states: np.ndarray

    def __len__(self) -> int:
        return len(self.actions)

    def take(self, index: np.ndarray) -> Transitions:
        return Transitions(self.states[index], self.actions[index], self.next_states[index])

    @staticmethod
    def concat(parts: list[Transitions]) -> Transitions:
        return Transitions(
            np.concatenate([p.states for p in parts]),
            np.concatenate([p.actions for p in parts]),
            np.concatenate([p.next_states for p in parts]),
        )
