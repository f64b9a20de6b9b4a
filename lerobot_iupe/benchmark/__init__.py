"""``lerobot-iupe-benchmark``: the paper's Tables 1 and 2 on this package — presets (what runs), runner (training
through lerobot-train, resumable records), evaluation (LeRobot's own) and report (tables and plots)."""

from lerobot_iupe.benchmark.evaluation import EVAL_SEED, evaluate_agent, evaluate_checkpoint, read_training_run
from lerobot_iupe.benchmark.presets import (
    ABLATION,
    CONTINUOUS,
    LOW_DATA,
    LOW_DATA_CONTINUOUS_METHODS,
    LOW_DATA_METHODS,
    METAWORLD,
    PRESETS,
    TABLE1_METHODS,
    DataSettings,
    EnvPreset,
    TrainBudget,
    method_flags,
)
from lerobot_iupe.benchmark.report import write_report
from lerobot_iupe.benchmark.runner import CHECKPOINT, Benchmark, Run, run_cli

__all__ = [
    "ABLATION",
    "CHECKPOINT",
    "CONTINUOUS",
    "EVAL_SEED",
    "LOW_DATA",
    "LOW_DATA_CONTINUOUS_METHODS",
    "LOW_DATA_METHODS",
    "METAWORLD",
    "PRESETS",
    "TABLE1_METHODS",
    "Benchmark",
    "DataSettings",
    "EnvPreset",
    "Run",
    "TrainBudget",
    "evaluate_agent",
    "evaluate_checkpoint",
    "method_flags",
    "read_training_run",
    "run_cli",
    "write_report",
]
