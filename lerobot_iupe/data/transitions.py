"""Aligned transitions: each action a_t with the frames around it, what the inverse dynamics model learns from."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def context_offsets(context: int) -> list[int]:
    """The frame offsets around t an IDM of ``context`` k reads: -k … k+1 (k = 0: the pair (s_t, s_{t+1}))."""
    return list(range(-context, context + 2))


@dataclass
class Transitions:
    """a_t with its window of frames (N, 2k+2, …) at offsets -k … k+1 of t (``context_offsets``), an episode's
    edges repeating its first or last frame; k = 0 is the paper's (s_t, a_t, s_{t+1})."""

    windows: np.ndarray
    actions: np.ndarray

    @classmethod
    def pairs(cls, states: np.ndarray, actions: np.ndarray, next_states: np.ndarray) -> Transitions:
        """(s_t, a_t, s_{t+1}) rows: windows of context 0."""
        return cls(np.stack([states, next_states], axis=1), actions)

    @classmethod
    def of_episode(cls, observations: np.ndarray, actions: np.ndarray, context: int) -> Transitions:
        """One episode's ``observations`` (T+1, …: s_0 … s_T) and ``actions`` (T, …) as windows of ``context``."""
        index = np.clip(np.arange(len(actions))[:, None] + np.asarray(context_offsets(context))[None], 0, len(actions))
        return cls(observations[index], actions)

    @property
    def context(self) -> int:
        return (self.windows.shape[1] - 2) // 2

    @property
    def states(self) -> np.ndarray:
        return self.windows[:, self.context]

    @property
    def next_states(self) -> np.ndarray:
        return self.windows[:, self.context + 1]

    def __len__(self) -> int:
        return len(self.actions)

    def take(self, index: np.ndarray) -> Transitions:
        return Transitions(self.windows[index], self.actions[index])

    @staticmethod
    def concat(parts: list[Transitions]) -> Transitions:
        return Transitions(np.concatenate([p.windows for p in parts]), np.concatenate([p.actions for p in parts]))
