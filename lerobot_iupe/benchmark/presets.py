"""What the benchmark runs: per env, the datasets to collect and the training budget of every method (typed;
turned into command-line flags only where a subprocess is started), the methods' switches, and the paper's
reference numbers."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

from lerobot.envs.configs import EnvConfig

from lerobot_iupe.envs.configs import env_cli_flags, env_config_from_settings
from lerobot_iupe.envs.metaworld_config import METAWORLD_MT10

# The paper's Table 1 (P, AER) and Table 2 (Maze 10×10, P, AER).
PAPER_TABLE1 = {
    "expert": {"cartpole": (1.0, 442.628), "acrobot": (1.0, -110.109), "mountaincar": (1.0, -147.265),
               "maze3": (1.0, 0.963), "maze5": (1.0, 0.970), "maze10": (1.0, 0.981)},
    "random": {"cartpole": (0.0, 18.7), "acrobot": (0.0, -482.6), "mountaincar": (0.0, -200.0),
               "maze3": (0.0, 0.557), "maze5": (0.0, 0.166), "maze10": (0.0, -0.415)},
    "bc": {"cartpole": (1.135, 500.0), "acrobot": (1.071, -83.59), "mountaincar": (1.56, -117.72),
           "maze3": (-1.207, 0.18), "maze5": (-0.921, -0.507), "maze10": (-0.47, -1.0)},
    "bco": {"cartpole": (1.135, 500.0), "acrobot": (0.98, -117.6), "mountaincar": (0.948, -150.0),
            "maze3": (0.883, 0.927), "maze5": (-0.112, 0.104), "maze10": (-0.416, -0.941)},
    "iupe": {"cartpole": (1.135, 500.0), "acrobot": (1.086, -78.1), "mountaincar": (1.314, -130.7),
             "maze3": (1.361, 0.927), "maze5": (1.0, 0.971), "maze10": (1.0, 0.981)},
    "ilpo": {"cartpole": (1.135, 500.0), "acrobot": (1.067, -85.3), "mountaincar": (0.626, -167.0),
             "maze3": (-1.711, -0.026), "maze5": (-0.398, -0.059), "maze10": (0.257, -0.020)},
}  # fmt: skip
PAPER_TABLE2 = {
    "bco": (-0.416, -0.941), "A": (-0.415, -0.94), "S": (0.534, 0.348), "E": (0.734, 0.605),
    "SA": (0.367, 0.088), "EA": (-0.407, -0.921), "SE": (0.943, 0.901), "iupe": (1.0, 0.981),
}  # fmt: skip
ABLATION = ["bco", "A", "S", "E", "SA", "EA", "SE", "iupe"]  # letters: Sampling, Exploration, Attention on
TABLE1_METHODS = ["expert", "random", "bc", "bco", "iupe", "ilpo", "ilpo_norm"]
# ILPO as the authors train it: the LPN for 100 epochs of batch 32 over the expert's state pairs (lerobot-train's
# --steps follow from the dataset), then 1,000 remapping env steps with ε = 0.2. It is selected as the other methods
# are: every 100 remapping steps, 10 episodes of its own played as lerobot-eval plays, the best kept.
ILPO_EPOCHS, ILPO_BATCH = 100, 32
ILPO_POLICY = {"selection_episodes": "10", "selection_every": "100"}
# ILPO as the authors' code runs it, and with its one documented deviation (--policy.normalize: vector states and
# their differences scaled per value; the authors' raw squared error lets MountainCar's velocity weigh nothing).
ILPO_VARIANTS = {"ilpo": {}, "ilpo_norm": {"normalize": "true"}}
ILPO_QUICK_POLICY = {"selection_episodes": "2", "selection_every": "100", "remap_steps": "200"}
LOW_DATA_METHODS = ["bco", "S", "E", "SE", "iupe"]


@dataclass(frozen=True)
class TrainBudget:
    """lerobot-train's budget of a trained method; ``policy`` holds further ``--policy.*`` settings,
    ``sampling_policy`` those of the methods whose sampling is on (settings of the sampling rule), and
    ``labelling_policy`` those of the methods whose policy learns from the IDM's labels (all but BC)."""

    steps: int
    batch_size: int
    cycle_steps: int
    policy: dict[str, str] = field(default_factory=dict)
    sampling_policy: dict[str, str] = field(default_factory=dict)
    labelling_policy: dict[str, str] = field(default_factory=dict)

    def flags(self, sampling: bool = True, labelling: bool = True) -> list[str]:
        policy = {**self.policy, **(self.sampling_policy if sampling else {})}
        policy.update(self.labelling_policy if labelling else {})
        return [
            f"--steps={self.steps}",
            f"--batch_size={self.batch_size}",
            f"--policy.cycle_steps={self.cycle_steps}",
            *[f"--policy.{name}={value}" for name, value in policy.items()],
        ]


@dataclass(frozen=True)
class DataSettings:
    """How the datasets of an env are collected: episode counts and lerobot-iupe-collect settings."""

    expert_episodes: int
    random_episodes: int
    random_start: bool = False  # maze: random pre-demonstrations start from a random cell
    random_max_steps: int = 0  # maze: step cap of the random pre-demonstrations (0: the env's)
    video: bool = True  # maze: MP4 video (true) or PNG frames in the parquet files (false)
    # The agent of the pre-demonstrations: "random" (uniform actions) or "play" (goal-agnostic play, for envs whose
    # uniform actions never reach the expert's states: lerobot-iupe-collect --agent=play).
    pre_demos_agent: str = "random"
    # Env settings of the pre-demonstrations' collection only (how the play agent plays): a run that never reads
    # the pre-demonstrations (BC, ILPO, the built-in agents) keeps its datasets and rows when they change.
    pre_demos_env: dict = field(default_factory=dict)

    def random_flags(self) -> list[str]:
        flags = ["--random_start=true"] if self.random_start else []
        return flags + ([f"--env.max_steps={self.random_max_steps}"] if self.random_max_steps else [])

    def data_flags(self) -> list[str]:
        return [] if self.video else ["--video=false"]


@dataclass(frozen=True)
class EnvPreset:
    env: dict  # EnvConfig fields, "type" included
    data: DataSettings
    train: TrainBudget
    eval_modes: tuple[str, ...] = ("argmax", "sample")
    """Every checkpoint is evaluated under both rules of ``--policy.eval_mode``: the most likely action (the
    categorical argmax, the Gaussian's mode: what ``lerobot-eval`` plays by default) and a draw."""
    methods: tuple[str, ...] | None = None
    """The methods this preset's column compares (None: every method asked for)."""

    def compared(self, methods: list[str]) -> list[str]:
        return [m for m in methods if self.methods is None or m in self.methods]

    @property
    def is_maze(self) -> bool:
        return self.env["type"] == "maze"

    @property
    def rollout_layouts(self) -> int:
        """Mazes: how many of the expert dataset's layouts (its last ones) the rollouts, and so the model
        selection, play (``--policy.rollout_layouts``); 0 = all."""
        return int(self.train.policy.get("rollout_layouts", 0))

    def _scored_demo_layouts(self, layouts: str | None) -> int:
        """How many demonstration layouts are scored (those the rollouts never play); 0 = no split."""
        return self.data.expert_episodes - self.rollout_layouts if layouts == "demo" and self.rollout_layouts else 0

    def env_config(self, layouts: str | None = None) -> EnvConfig:
        """The evaluation env; demonstration layouts: only those the rollouts never play (the first ones)."""
        settings = {**self.env, **({"layouts": layouts} if layouts else {})}
        if scored := self._scored_demo_layouts(layouts):
            settings["num_layouts"] = scored
        return env_config_from_settings(settings)

    def scored_episodes(self, layouts: str | None, episodes: int) -> int:
        """Evaluation episodes on a layout set: at most one per layout on the demonstration layouts left to it."""
        scored = self._scored_demo_layouts(layouts)
        return min(episodes, scored) if scored else episodes

    def env_flags(self) -> list[str]:
        return env_cli_flags(self.env)

    @property
    def layouts(self) -> list[str | None]:
        """Evaluation layout sets: mazes on demonstration and held-out layouts."""
        return ["demo", "heldout"] if self.is_maze else [None]

    def data_key(self, quick: bool) -> str:
        """Short hash of everything that determines the datasets: a changed preset collects new ones."""
        data = self.data
        key = [self.env, data.expert_episodes, data.random_episodes, data.random_flags(), data.data_flags(), quick]
        # the default agent stays out of the hash, so the committed rows of random pre-demonstrations keep their keys
        return digest(key if data.pre_demos_agent == "random" else [*key, data.pre_demos_agent])

    def pre_demos_key(self, quick: bool) -> str:
        """``data_key`` of the pre-demonstrations, which also depends on ``pre_demos_env``."""
        data_key = self.data_key(quick)
        return digest([data_key, self.data.pre_demos_env]) if self.data.pre_demos_env else data_key

    def pre_demos_flags(self) -> list[str]:
        """lerobot-iupe-collect's flags of the pre-demonstrations: the env's, with ``pre_demos_env`` over them."""
        return env_cli_flags({**self.env, **self.data.pre_demos_env})


def digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:10]


VECTOR_BUDGET = TrainBudget(steps=400, batch_size=128, cycle_steps=100)
# Mazes at 3 px per maze block (2N+1 blocks a side; 10×10 at 2 px) stored as PNG frames: the CNN's cost grows with
# the pixel count (IDM step of 64 at 21 px 15 ms, at 63 px 61 ms); LeRobot's loader reads a PNG 8x faster than video.
# Mazes follow the paper's protocol (evaluation on the demonstration layouts), but the model is selected on
# rollouts: those play the last 20 of the 100 demonstration layouts, and the demonstration-layout evaluation plays
# the other 80, so selection never sees an evaluated layout.
SELECT_APART = {"rollout_layouts": "20"}
PRESETS = {
    "cartpole": EnvPreset({"type": "cartpole"}, DataSettings(10, 400), VECTOR_BUDGET),
    "acrobot": EnvPreset({"type": "acrobot"}, DataSettings(10, 40), VECTOR_BUDGET),
    "mountaincar": EnvPreset(
        {"type": "mountaincar"}, DataSettings(10, 100), TrainBudget(1000, 128, 200, {"optimizer_lr": "1e-2"})
    ),
    "maze3": EnvPreset(
        {"type": "maze", "size": 3, "image_size": 21},
        DataSettings(100, 400, random_start=True, random_max_steps=15, video=False),
        TrainBudget(1000, 64, 200, SELECT_APART),
    ),
    "maze5": EnvPreset(
        {"type": "maze", "size": 5, "image_size": 33},
        DataSettings(100, 400, random_start=True, random_max_steps=25, video=False),
        TrainBudget(1500, 64, 250, SELECT_APART),
    ),
    "maze10": EnvPreset(
        {"type": "maze", "size": 10, "image_size": 42},
        DataSettings(100, 400, random_start=True, random_max_steps=60, video=False),
        TrainBudget(2000, 64, 250, {"idm_epochs": "2", **SELECT_APART}),
    ),
}
# Continuous actions (the "continuous" table): 10 rollout episodes per cycle, since a hovering lander plays all
# 1,000 steps of an episode and rollouts are most of a run's time.
# SO-101 (benchmarks/pre_demos.md, history.md): play pre-demonstrations, since uniform random joint deltas never
# carry the arm where the expert goes; an IDM reading the arm's state only (R² 0.957 on the expert against -0.32
# reading the block it never saw carried); a policy reading 4 observations (the expert's gripper holds are a
# hidden phase: BC 0.37 -> 0.65).
SO101_POLICY = {
    "rollout_episodes": "10",
    "selection_episodes": "10",
    "n_obs_steps": "4",
    "idm_observation_keys": "[observation.state]",
}
# The task's own rows also see the block and the goal from the end effector (--env.relative_positions) and play the
# grasp open or shut (--policy.binary_action_dims=[3]): SO-101 BC 0.72 -> 0.89 (history.md, findings.md).
SO101_ENV = {"type": "so101_pickplace", "relative_positions": True}
SO101_TASK_POLICY = {**SO101_POLICY, "binary_action_dims": "[3]"}
# IUPE keeps a fifth of its IDM's data from the play pre-demonstrations when every rollout succeeds: with the
# paper's share of 1 the IDM's held-out R² fell in each such cycle (0.94-0.96 -> 0.85-0.92; findings.md).
SO101_SAMPLING = {"max_success_share": "0.8"}
# LunarLander trains 6,000 steps (30 cycles): at 3,000 IUPE's selection success was still rising at the last cycle
# (seed 2: 0.85), and the same run trained on to 6,000 scored P 0.990 by the mode against 0.839 (findings.md).
# LunarLander selects BC, BCO(α) and IUPE alike on 20 episodes of their own per cycle played by the mode (fixed
# start seeds): on 10, neighbouring cycles of one seed differed by 0.1-0.4 in success (benchmarks/findings.md).
# SO-101 on 10 (its episodes are slow to simulate); BC plays them every cycle_steps too, so that no method keeps
# a checkpoint the others would have passed over (neighbouring SO-101 checkpoints differ by tens of points).
LUNAR_POLICY = {"rollout_episodes": "10", "selection_episodes": "20"}
CONTINUOUS = {
    "lunarlander": EnvPreset({"type": "lunarlander"}, DataSettings(20, 200), TrainBudget(6000, 64, 200, LUNAR_POLICY)),
    "so101_pickplace": EnvPreset(
        SO101_ENV,
        DataSettings(50, 100, pre_demos_agent="play"),
        TrainBudget(3000, 64, 200, SO101_TASK_POLICY, SO101_SAMPLING),
    ),
    # The same task and budget from uniformly random pre-demonstrations, with the observation and heads its rows
    # were measured with: what the learners from state-only data make of them (BC, the expert and random rows do
    # not depend on the pre-demonstrations).
    "so101_uniform": EnvPreset(
        {"type": "so101_pickplace"},
        DataSettings(50, 100),
        TrainBudget(3000, 64, 200, SO101_POLICY),
        methods=("bco", "iupe"),
    ),
}
# Meta-World's MT10 through LeRobot's own env, observed as state (--env.type=metaworld_state): 10 scripted-expert
# demonstrations per task, as the 3D Diffusion Policy paper; 20 play episodes (10,000 transitions) of
# pre-demonstrations; 1,000 steps, a cycle every 200 with 10 rollout and 10 selection episodes (IUPE on push: its
# selection success rose 0.2 -> 0.6 over the first four cycles). Scored by the mode, lerobot-eval's default rule.
# The methods that label with an IDM read the hand's state (agent_pos) over frames t-3 … t+4: the hand follows a
# command 3-4 steps late, and play never moves the objects. On push the cycle's first IDM (trained on play) labels
# the expert's hand moves x/y/z at R² 0.89/0.84/0.36 so, against 0.42/0.23/0.15 reading the pair of all 43 values
# (benchmarks/cycle_context.md).
METAWORLD_POLICY = {"rollout_episodes": "10", "selection_episodes": "10"}
# Half of play's moves hold one command for 10-40 steps, as the scripted experts do: the cycle's first IDM then
# labels button-press-topdown's y at R² 0.43 instead of -0.99 (benchmarks/cycle_play.md), and IUPE's success there
# rose from 3 to 94 % (benchmarks/metaworld/results.md). Play that also grasps the object (play_object_moves 0.25)
# lifts pick-place but lowers reach and peg-insert-side over six seeds (benchmarks/metaworld/trailing_tasks.md).
METAWORLD_PLAY = {"play_held_moves": 0.5}
METAWORLD_LABELLING = {"idm_context": "3", "idm_observation_keys": "[observation.state]"}
METAWORLD = {
    f"mw-{task.removesuffix('-v3')}": EnvPreset(
        {"type": "metaworld_state", "task": task},
        DataSettings(10, 20, pre_demos_agent="play", pre_demos_env=METAWORLD_PLAY),
        TrainBudget(1000, 64, 200, METAWORLD_POLICY, labelling_policy=METAWORLD_LABELLING),
        eval_modes=("argmax",),
    )
    for task in METAWORLD_MT10
}
# Other papers' success rates (%) on these tasks, under their own protocols: the 3D Diffusion Policy paper (Ze et al.,
# 2024, Table XVIII; 10 scripted demonstrations, 3 seeds, the mean of its 5 best evaluations of 20 episodes): DP3 from
# point clouds and Diffusion Policy from images, both with the expert's actions.
METAWORLD_ANCHORS = {
    "DP3": {"reach": 24, "push": 51, "pick-place": 12, "door-open": 99, "drawer-open": 100, "drawer-close": 100,
            "button-press-topdown": 100, "peg-insert-side": 69, "window-open": 100, "window-close": 100},
    "Diffusion Policy (images)": {"reach": 18, "push": 30, "pick-place": 0, "door-open": 98, "drawer-open": 93,
                                  "drawer-close": 100, "button-press-topdown": 98, "peg-insert-side": 34,
                                  "window-open": 100, "window-close": 100},
}  # fmt: skip
# Low data: one expert episode and about 1,000 pre-demonstration transitions.
LOW_DATA_CONTINUOUS_METHODS = ["bco", "iupe"]
LOW_DATA = {
    "cartpole": EnvPreset({"type": "cartpole"}, DataSettings(1, 45), TrainBudget(200, 64, 25)),
    "acrobot": EnvPreset({"type": "acrobot"}, DataSettings(1, 2), TrainBudget(200, 64, 25)),
    "mountaincar": EnvPreset({"type": "mountaincar"}, DataSettings(1, 5), TrainBudget(400, 64, 50)),
    "lunarlander": EnvPreset(
        {"type": "lunarlander"},
        DataSettings(1, 10),
        TrainBudget(1000, 64, 100, {"rollout_episodes": "10"}),
        methods=tuple(LOW_DATA_CONTINUOUS_METHODS),
    ),
}
QUICK_BUDGET = TrainBudget(20, 32, 10, {"rollout_episodes": "4"})


def ilpo_steps(pairs: int) -> int:
    """lerobot-train steps of ILPO's LPN on ``pairs`` expert state pairs: ``ILPO_EPOCHS`` epochs of ``ILPO_BATCH``."""
    return -(-pairs // ILPO_BATCH) * ILPO_EPOCHS


def policy_type(method: str) -> str:
    """The ``--policy.type`` a method trains: ILPO its own, every other method is the IUPE policy's."""
    return "ilpo" if method in ILPO_VARIANTS else "iupe"


def mechanisms_on(method: str) -> str:
    """The IUPE mechanisms a method runs with: S (sampling), E (exploration), A (attention); ablation variants
    are named by them, BCO(α) has none, BC is not a cycle."""
    return {"iupe": "SEA", "bco": "", "bc": ""}.get(method, method)


def samples(method: str) -> bool:
    """Whether the method rebuilds I^s by the sampling rule (its budget then carries the sampling settings)."""
    return method != "bc" and "S" in mechanisms_on(method)


def method_flags(method: str) -> list[str]:
    """lerobot-train flags of a method; ablation variants name the mechanisms that are on."""
    if method == "bc":
        return ["--policy.supervised=true"]
    if method == "iupe" or method in ILPO_VARIANTS:
        return []
    on = mechanisms_on(method)
    return [
        f"--policy.sampling={'S' in on}".lower(),
        f"--policy.exploration={'E' in on}".lower(),
        f"--policy.attention={'A' in on}".lower(),
    ]
