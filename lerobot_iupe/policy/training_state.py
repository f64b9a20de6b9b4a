"""What the IUPE cycle carries from step to step, and how it is saved beside a checkpoint."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from lerobot_iupe.data.transitions import Transitions

TRAINING_STATE_FILE = "iupe_training_state.pt"
CYCLES_FILE = "iupe_cycles.jsonl"


@dataclass
class TrainingState:
    """What the cycle carries from step to step; all of it but ``pre`` and ``pre_held`` (read again, and split
    again identically, on resume) is saved beside a checkpoint."""

    seed: int
    rank: int
    pre: Transitions | None  # the IDM's part of I_pre (I^s is drawn from it); None: a supervised run
    pre_held: Transitions | None  # the rest: scores the IDM every cycle and is never trained on
    sampled_set_size: int
    rng: np.random.Generator
    torch_rng: torch.Generator | None  # None where the policy runs on another device (then: the global one)
    idm_optimizer: torch.optim.Optimizer | None  # None: supervised, LeRobot's optimizer trains the IDM
    step: int = 0
    cycle: int = 0
    best_success: float = -1.0  # the goal rate r of the selected cycle
    best_env_success: float = -1.0  # and its rate of the env's own success (selection compares this first)
    rollouts_s: float = 0.0  # cumulative seconds, for the benchmark's time breakdown
    idm_s: float = 0.0
    selection_s: float = 0.0  # episodes played only to select the model
    cycles: list[dict] = field(default_factory=list)

    def saved(self, latest_weights: dict[str, Tensor]) -> dict:
        return {
            "step": self.step,
            "cycle": self.cycle,
            "best_success": self.best_success,
            "best_env_success": self.best_env_success,
            "seed": self.seed,
            "rng": self.rng.bit_generator.state,
            "torch_rng": None if self.torch_rng is None else self.torch_rng.get_state(),
            "idm_optimizer": None if self.idm_optimizer is None else self.idm_optimizer.state_dict(),
            "latest_weights": latest_weights,
            "seconds": {"rollouts": self.rollouts_s, "idm": self.idm_s, "selection": self.selection_s},
            "cycles": self.cycles,
        }

    def restore(self, saved: dict) -> None:
        self.step, self.cycle, self.best_success, self.seed = (
            saved["step"], saved["cycle"], saved["best_success"], saved["seed"],
        )  # fmt: skip
        self.best_env_success = saved.get("best_env_success", self.best_success)  # states saved before it existed
        self.rollouts_s, self.idm_s = saved["seconds"]["rollouts"], saved["seconds"]["idm"]
        self.selection_s = saved["seconds"].get("selection", 0.0)
        self.rng.bit_generator.state = saved["rng"]
        if self.torch_rng is not None and saved["torch_rng"] is not None:
            self.torch_rng.set_state(saved["torch_rng"])
        if self.idm_optimizer is not None:
            self.idm_optimizer.load_state_dict(saved["idm_optimizer"])
        self.cycles = list(saved["cycles"])
