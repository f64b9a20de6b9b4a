"""A benchmark run — one method and seed on an env's datasets — and the keys that say which recorded rows it
produces."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from lerobot_iupe.benchmark.evaluation import EVAL_SEED
from lerobot_iupe.benchmark.presets import (
    ILPO_BATCH,
    ILPO_EPOCHS,
    ILPO_POLICY,
    ILPO_QUICK_POLICY,
    ILPO_VARIANTS,
    QUICK_BUDGET,
    EnvPreset,
    digest,
    ilpo_steps,
    method_flags,
    samples,
)
from lerobot_iupe.policy.configuration_iupe import IUPEConfig


def config_key(
    preset: EnvPreset,
    quick: bool,
    train_flags: list[str],
    eval_episodes: int,
    plays_selection_episodes: bool,
    reads_pre_demos: bool = False,
) -> str:
    """Hash of everything that determines a run's rows: datasets (the pre-demonstrations' only for a run that
    reads them), training flags, evaluation."""
    data_key = preset.pre_demos_key(quick) if reads_pre_demos else preset.data_key(quick)
    key = [data_key, train_flags, eval_episodes, preset.eval_modes]
    if preset.rollout_layouts:  # the evaluated layouts depend on it (also for the built-in agents)
        key.append([preset.scored_episodes(layouts, eval_episodes) for layouts in preset.layouts])
    if plays_selection_episodes:  # rows selected on the exploring rollouts (older code) are not these
        key.append("selection on episodes played as lerobot-eval plays")
    return digest(key)


def agent_config_key(preset: EnvPreset, quick: bool, eval_episodes: int) -> str:
    """``config_key`` of a built-in agent's rows (nothing trained, nothing selected)."""
    return config_key(preset, quick, [], eval_episodes, plays_selection_episodes=False)


@dataclass
class Run:
    """One cell entry to produce: a method (and training seed) on an env's datasets."""

    table: str
    name: str
    preset: EnvPreset
    method: str
    seed: int | None
    data: dict[str, Path]
    references: dict[str | None, tuple[float, float]]  # eval layouts → (R_expert, R_random)
    quick: bool = False

    @property
    def train_flags(self) -> list[str]:
        """lerobot-train's flags of the method's budget (ILPO: all but --steps, which its data sets: ``steps``)."""
        if self.method in ILPO_VARIANTS:
            policy = {**(ILPO_QUICK_POLICY if self.quick else ILPO_POLICY), **ILPO_VARIANTS[self.method]}
            if self.preset.rollout_layouts and not self.quick:
                policy["rollout_layouts"] = str(self.preset.rollout_layouts)
            return [f"--batch_size={ILPO_BATCH}", *[f"--policy.{k}={v}" for k, v in policy.items()]]
        return [*self.budget.flags(samples(self.method), self.method != "bc"), *method_flags(self.method)]

    @property
    def steps(self) -> int:
        """lerobot-train's --steps: the budget's; ILPO's from the expert dataset (``ilpo_steps``)."""
        if self.method not in ILPO_VARIANTS or self.quick:
            return self.budget.steps
        info = json.loads((self.data["expert"] / "meta" / "info.json").read_text())
        return ilpo_steps(info["total_frames"] - info["total_episodes"])

    @property
    def budget(self):
        return QUICK_BUDGET if self.quick else self.preset.train

    def config_key(self, eval_episodes: int) -> str:
        """Hash of everything that determines this run's rows: datasets, training flags, evaluation."""
        if self.method in ("expert", "random"):
            return agent_config_key(self.preset, self.quick, eval_episodes)
        flags = self.train_flags + ([f"ilpo epochs {ILPO_EPOCHS}"] if self.method in ILPO_VARIANTS else [])
        return config_key(
            self.preset, self.quick, flags, eval_episodes, self.plays_selection_episodes, self.reads_pre_demos
        )

    @property
    def reads_pre_demos(self) -> bool:
        """Whether the run learns from the pre-demonstrations (IUPE and BCO(α)'s IDM), not BC, ILPO or an agent."""
        return self.method not in ("expert", "random", "bc", *ILPO_VARIANTS)

    @property
    def plays_selection_episodes(self) -> bool:
        """Whether the run selects its model on episodes of its own (its rollouts explore: IUPE's default; BC when
        the preset gives selection episodes)."""
        if self.method in ("expert", "random", *ILPO_VARIANTS):
            return False
        policy = dict(f.removeprefix("--policy.").split("=", 1) for f in self.train_flags if f.startswith("--policy."))
        config = IUPEConfig(  # the config's own rule, from the settings it depends on
            device="cpu",
            supervised=policy.get("supervised", "false") == "true",
            exploration=policy.get("exploration", "true") == "true",
            eval_mode=policy.get("eval_mode", "argmax"),
            selection_episodes=int(policy["selection_episodes"]) if "selection_episodes" in policy else None,
        )
        return config.separate_selection_episodes > 0

    @property
    def cost(self) -> float:
        """Rough relative duration (training steps × pixels), to start the longest runs first."""
        if self.method in ("expert", "random"):
            return 0.0
        return (
            self.preset.train.steps * self.preset.env.get("image_size", 1) ** 2 * (0.3 if self.method == "bc" else 1.0)
        )


def selection_rule(run: Run, checkpoint: Path, cycles: list[dict]) -> str:
    """How a run's checkpoint was chosen, in words (recorded with each of its rows)."""
    if run.method in ILPO_VARIANTS:
        if not cycles:
            return "ILPO: the final remapping network (no selection)"
        config = json.loads((checkpoint / "config.json").read_text())
        played = "a draw" if config["eval_mode"] == "sample" else "the mode"
        return (
            f"ILPO: the remapping network of the best of {len(cycles)} points (every {config['selection_every']} "
            "remapping steps) on "
            f"{cycles[0]['selection_episodes']} episodes of its own played by {played}, the same start seeds each "
            "time (the env's success, then the goal), latest on ties"
        )
    if not cycles:
        return "the last step's weights (no selection)"
    config = json.loads((checkpoint / "config.json").read_text())
    episodes, layouts = config["rollout_episodes"], config.get("rollout_layouts", 0)
    if not run.preset.is_maze:
        where = f"seeds ≥ 1,000,000 (evaluation: {EVAL_SEED}…)"
    elif layouts:
        where = f"the last {layouts} demonstration layouts, which the demonstration-layout evaluation does not play"
    else:
        where = "the expert dataset's own (demonstration) layouts, which the evaluation also plays"
    judged_by_env = "env_success_rate" in cycles[0] or "selection_env_success_rate" in cycles[0]
    rule = "the env's success, then the goal reached at any step, " if judged_by_env else ""
    if cycles[0].get("selection_s") is not None and cycles[-1]["selection_s"] > 0:
        played = "a draw" if config.get("eval_mode") == "sample" else "the mode"
        return (
            f"best success of a cycle on {cycles[0]['selection_episodes']} episodes of its own played by {played} "
            f"(as lerobot-eval plays), the same start seeds every cycle ({rule}{len(cycles)} cycles, latest on "
            f"ties), on {where}"
        )
    return (
        f"best rollout success of a cycle ({rule}{len(cycles)} cycles × {episodes} episodes, latest on ties), "
        f"on {where}"
    )


def training_env_steps(run: Run, checkpoint: Path, cycles: list[dict]) -> dict[str, int] | None:
    """The env steps a run cost, by what took them: the pre-demonstrations it learned from (IUPE, BCO(α)), its own
    online play (IUPE's rollouts, ILPO's remapping) and the episodes played only to select the model. None where
    the cycle records predate the counts."""
    pre = 0
    if run.reads_pre_demos:
        pre = json.loads((run.data["random"] / "meta" / "info.json").read_text())["total_frames"]
    if run.method in ILPO_VARIANTS:
        summary = json.loads((checkpoint / "ilpo_remapping.json").read_text())
        online, selection = summary["remap_env_steps"], summary["selection_env_steps"]
    else:
        if cycles and any("selection_env_steps" not in c for c in cycles):
            return None
        online = sum(c.get("rollout_env_steps", 0) for c in cycles)
        selection = sum(c.get("selection_env_steps", 0) for c in cycles)
    return {"pre_demonstrations": pre, "online": online, "selection": selection}
