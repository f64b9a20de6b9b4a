"""The paper's Tables 1 and 2 on this package: Expert, Random, BC, BCO(α) and IUPE (and the ablation variants),
each trained through ``lerobot-train`` and evaluated with LeRobot's own evaluation code (``eval_policy_all``,
what ``lerobot-eval`` runs, without its video rendering).

Every finished run is appended to ``<work>/runs.jsonl`` at once, so an interrupted benchmark resumes where it
stopped; the report (results.md/json, plots) is rebuilt from all records on every call.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from lerobot.configs import PreTrainedConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.envs.configs import EnvConfig
from lerobot.policies import make_policy, make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.utils.random_utils import set_seed

from lerobot_iupe.algorithm import performance
from lerobot_iupe.dataset_utils import read_iupe_meta
from lerobot_iupe.experts import reference_returns
from lerobot_iupe.modeling_iupe import CYCLES_FILE

BIN = Path(sys.executable).parent
EVAL_SEED = 500_000  # evaluation seeds/layouts 500000…: never used by data (0…, 1000…) or rollouts (≥ 1e6)
CHECKPOINT = "checkpoints/last/pretrained_model"

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
}  # fmt: skip
PAPER_TABLE2 = {
    "bco": (-0.416, -0.941), "A": (-0.415, -0.94), "S": (0.534, 0.348), "E": (0.734, 0.605),
    "SA": (0.367, 0.088), "EA": (-0.407, -0.921), "SE": (0.943, 0.901), "iupe": (1.0, 0.981),
}  # fmt: skip
ABLATION = ["bco", "A", "S", "E", "SA", "EA", "SE", "iupe"]  # letters: Sampling, Exploration, Attention on


@dataclass
class EnvPreset:
    env: dict  # EnvConfig fields, "type" included
    expert_episodes: int
    random_episodes: int
    train: list[str]  # lerobot-train flags of the trained methods
    random_flags: list[str] = field(default_factory=list)
    data_flags: list[str] = field(default_factory=list)  # lerobot-iupe-collect flags of every dataset

    @property
    def is_maze(self) -> bool:
        return self.env["type"] == "maze"

    def env_config(self, layouts: str | None = None) -> EnvConfig:
        fields = {k: v for k, v in self.env.items() if k != "type"}
        if layouts:
            fields["layouts"] = layouts
        return EnvConfig.get_choice_class(self.env["type"])(**fields)

    def env_flags(self) -> list[str]:
        return [f"--env.{k}={v}" for k, v in self.env.items()]

    @property
    def eval_modes(self) -> tuple[str, ...]:
        """Every maze checkpoint is evaluated both ways (an argmax policy that bumps into a wall stays put until
        the step cap); vector policies by argmax."""
        return ("argmax", "sample") if self.is_maze else ("argmax",)

    def data_key(self, quick: bool) -> str:
        """Short hash of everything that determines the datasets: a changed preset collects new ones."""
        return digest([self.env, self.expert_episodes, self.random_episodes, self.random_flags, self.data_flags, quick])


def digest(value) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:10]


VECTOR_TRAIN = ["--steps=400", "--batch_size=128", "--policy.cycle_steps=100"]
MAZE_RANDOM = ["--random_start=true"]
# Mazes at 3 px per maze block (2N+1 blocks a side; 10×10 at 2 px) stored as PNG frames: the CNN's cost grows with
# the pixel count (IDM step of 64 at 21 px 15 ms, at 63 px 61 ms); LeRobot's loader reads a PNG 8x faster than video.
MAZE_DATA = ["--video=false"]
PRESETS = {
    "cartpole": EnvPreset({"type": "cartpole"}, 10, 400, VECTOR_TRAIN),
    "acrobot": EnvPreset({"type": "acrobot"}, 10, 40, VECTOR_TRAIN),
    "mountaincar": EnvPreset({"type": "mountaincar"}, 10, 100, ["--steps=1000", "--batch_size=128",
                             "--policy.cycle_steps=200", "--policy.optimizer_lr=1e-2"]),
    "maze3": EnvPreset({"type": "maze", "size": 3, "image_size": 21}, 100, 400, ["--steps=1000", "--batch_size=64",
                       "--policy.cycle_steps=200"], MAZE_RANDOM + ["--env.max_steps=15"], MAZE_DATA),
    "maze5": EnvPreset({"type": "maze", "size": 5, "image_size": 33}, 100, 400, ["--steps=1500", "--batch_size=64",
                       "--policy.cycle_steps=250"], MAZE_RANDOM + ["--env.max_steps=25"], MAZE_DATA),
    "maze10": EnvPreset({"type": "maze", "size": 10, "image_size": 42}, 100, 400, ["--steps=2000",
                        "--batch_size=64", "--policy.cycle_steps=250", "--policy.idm_epochs=2"],
                        MAZE_RANDOM + ["--env.max_steps=60"], MAZE_DATA),
}  # fmt: skip
# Low data: one expert episode and about 1,000 pre-demonstration transitions.
LOW_DATA = {
    "cartpole": EnvPreset({"type": "cartpole"}, 1, 45, ["--steps=200", "--batch_size=64", "--policy.cycle_steps=25"]),
    "acrobot": EnvPreset({"type": "acrobot"}, 1, 2, ["--steps=200", "--batch_size=64", "--policy.cycle_steps=25"]),
    "mountaincar": EnvPreset({"type": "mountaincar"}, 1, 5, ["--steps=400", "--batch_size=64",
                             "--policy.cycle_steps=50"]),
}  # fmt: skip
QUICK_TRAIN = ["--steps=20", "--batch_size=32", "--policy.cycle_steps=10", "--policy.rollout_episodes=4"]


def method_flags(method: str) -> list[str]:
    """lerobot-train flags of a method; ablation variants name the mechanisms that are on."""
    if method == "bc":
        return ["--policy.supervised=true"]
    if method == "iupe":
        return []
    on = "" if method == "bco" else method
    return [
        f"--policy.sampling={'S' in on}".lower(),
        f"--policy.exploration={'E' in on}".lower(),
        f"--policy.attention={'A' in on}".lower(),
    ]


def train_steps(train_flags: list[str]) -> int:
    """The ``--steps=`` value of a list of lerobot-train flags."""
    return int(next(f for f in train_flags if f.startswith("--steps=")).split("=")[1])


def run_cli(*args: str, log: Path | None = None, echo: bool = False, threads: int = 0) -> str:
    """Run a console script, printing its command line (and its output with ``echo``); the output is returned
    and written to ``log``. ``threads`` > 0 caps its CPU threads (OMP_NUM_THREADS)."""
    print("$", shlex.join(args), flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)} if threads else None
    process = subprocess.Popen(
        [str(BIN / args[0]), *args[1:]], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    lines = []
    for line in process.stdout:
        lines.append(line)
        if echo:
            print(line, end="", flush=True)
    output = "".join(lines)
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(output)
    if process.wait() != 0:
        raise RuntimeError(f"{args[0]} failed ({process.returncode}); see {log}\n{output[-2000:]}")
    return output


def collect_datasets(
    name: str, preset: EnvPreset, data_dir: Path, quick: bool = False, threads: int = 0
) -> dict[str, Path]:
    """Expert (state only), the same expert episodes with actions (for BC), random pre-demonstrations."""
    paths = {}
    name = f"{name}-{preset.data_key(quick)}"
    n_expert, n_random = (min(preset.expert_episodes, 5), min(preset.random_episodes, 60)) if quick else (
        preset.expert_episodes, preset.random_episodes)  # fmt: skip
    for kind, agent, episodes, extra in [
        ("expert", "expert", n_expert, ["--seed=0"]),
        ("expert-actions", "expert", n_expert, ["--seed=0", "--keep_actions=true"]),
        ("random", "random", n_random, ["--seed=1000", *preset.random_flags]),
    ]:
        root = data_dir / f"{name}-{kind}"
        if not (root / "meta" / "iupe.json").exists():
            run_cli(
                "lerobot-iupe-collect", *preset.env_flags(), f"--agent={agent}", f"--episodes={episodes}", *extra,
                *preset.data_flags,
                f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", "--overwrite=true",
                threads=threads,
            )  # fmt: skip
        paths[kind] = root
    return paths


@torch.no_grad()
def evaluate_checkpoint(
    checkpoint: Path, env_cfg: EnvConfig, episodes: int, eval_mode: str = "argmax", seed: int = EVAL_SEED
) -> dict:
    """What lerobot-eval does (make_env, make_policy, LeRobot's processors, eval_policy_all), minus videos;
    ``eval_mode`` is ``--policy.eval_mode``."""
    set_seed(seed)
    policy_cfg = PreTrainedConfig.from_pretrained(checkpoint)
    policy_cfg.pretrained_path = checkpoint
    policy_cfg.device = "cpu"
    policy_cfg.eval_mode = eval_mode
    envs = make_env(env_cfg, n_envs=min(episodes, 50), use_async_envs=False)
    policy = make_policy(cfg=policy_cfg, env_cfg=env_cfg).eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=policy_cfg,
        pretrained_path=str(checkpoint),
        preprocessor_overrides={"device_processor": {"device": "cpu"}},
    )
    env_pre, env_post = make_env_pre_post_processors(env_cfg=env_cfg, policy_cfg=policy_cfg)
    info = eval_policy_all(
        envs=envs, policy=policy, env_preprocessor=env_pre, env_postprocessor=env_post, preprocessor=preprocessor,
        postprocessor=postprocessor, n_episodes=episodes, start_seed=seed,
    )  # fmt: skip
    close_envs(envs)
    return info["overall"]


def evaluate_agent(agent: str, env_cfg: EnvConfig, episodes: int) -> dict:
    """A built-in agent on the evaluation seeds (the same envs, seeds and layouts as ``evaluate_checkpoint``).
    Not through eval_policy_all: the maze expert reads the simulator's state, which a LeRobot policy cannot."""
    returns = reference_returns(env_cfg, agent, episodes, seed=EVAL_SEED)
    return {"avg_sum_reward": float(returns.mean()), "pc_success": None}


DATA_S = re.compile(r"data_s:([\d.]+)")


def read_training_run(checkpoint: Path, output: str, steps: int) -> tuple[list[dict], dict]:
    """The run's cycle records (``iupe_cycles.jsonl`` beside the checkpoint) and its time breakdown."""
    path = checkpoint / CYCLES_FILE
    cycles = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
    data_avg = [float(x) for x in DATA_S.findall(output)]  # LeRobot's own per-step data-loading average
    timing = {
        "rollouts_s": cycles[-1]["rollouts_s"] if cycles else 0.0,
        "idm_s": cycles[-1]["idm_s"] if cycles else 0.0,
        "data_loading_s": float(np.mean(data_avg)) * steps if data_avg else 0.0,
    }
    return cycles, timing


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
        return [*(QUICK_TRAIN if self.quick else self.preset.train), *method_flags(self.method)]

    def config_key(self, eval_episodes: int) -> str:
        """Hash of everything that determines this run's rows: datasets, training flags, evaluation."""
        train = [] if self.method in ("expert", "random") else self.train_flags
        return digest([self.preset.data_key(self.quick), train, eval_episodes, self.preset.eval_modes])

    @property
    def cost(self) -> float:
        """Rough relative duration (training steps × pixels), to start the longest runs first."""
        if self.method in ("expert", "random"):
            return 0.0
        return (
            train_steps(self.preset.train)
            * self.preset.env.get("image_size", 1) ** 2
            * (0.3 if self.method == "bc" else 1.0)
        )


@dataclass
class Benchmark:
    work: Path
    eval_episodes: int = 100
    quick: bool = False
    echo: bool = False  # stream lerobot-train's output (the demo) instead of only logging it
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def records_file(self) -> Path:
        return self.work / "runs.jsonl"

    @property
    def calls_file(self) -> Path:
        return self.work / "calls.jsonl"

    def log_call(self, command: str, seconds: float) -> list[dict]:
        """Record one call of the benchmark (its command line and wall-clock); return all calls so far."""
        self.work.mkdir(parents=True, exist_ok=True)
        with self.calls_file.open("a") as f:
            f.write(json.dumps({"command": command, "seconds": seconds}) + "\n")
        return [json.loads(line) for line in self.calls_file.read_text().splitlines() if line.strip()]

    def records(self) -> list[dict]:
        if not self.records_file.exists():
            return []
        return [json.loads(line) for line in self.records_file.read_text().splitlines() if line.strip()]

    def _save(self, record: dict) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        with self.records_file.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def _done(self, run: Run) -> bool:
        key = (run.table, run.name, run.method, run.seed, run.config_key(self.eval_episodes))
        return any((r["table"], r["env"], r["method"], r["seed"], r.get("config")) == key for r in self.records())

    def references(self, preset: EnvPreset, data: dict[str, Path]) -> dict[str | None, tuple[float, float]]:
        """Per evaluation layout set: R_expert = mean return of the expert demonstrations (held-out maze layouts:
        of the expert on 100 of them), R_random = uniform-random policy, 100 episodes (seeds 100000…)."""
        references = {}
        for layouts in self.layouts(preset):
            env_cfg = preset.env_config(layouts)
            if layouts == "heldout":
                expert = float(reference_returns(env_cfg, "expert", 100).mean())
            else:
                expert = read_iupe_meta(data["expert"])["mean_return"]
            references[layouts] = (expert, float(reference_returns(env_cfg, "random", 100).mean()))
        return references

    def layouts(self, preset: EnvPreset) -> list[str | None]:
        return ["demo", "heldout"] if preset.is_maze else [None]

    def plan(
        self,
        table: str,
        name: str,
        preset: EnvPreset,
        methods: list[str],
        seeds: list[int],
        threads: int = 0,
    ) -> list[Run]:
        """The unrecorded runs of ``methods`` × ``seeds`` (a run is recorded when a row with its table, env, method,
        seed and configuration key exists), collecting the datasets and measuring the references first."""
        data = collect_datasets(name, preset, self.work / "data", self.quick, threads)
        references = self.references(preset, data)
        runs = [
            Run(table, name, preset, method, seed, data, references, self.quick)
            for method in methods
            for seed in ([None] if method in ("expert", "random") else seeds)
        ]
        return [run for run in runs if not self._done(run)]

    def plan_all(self, requests: list[dict], jobs: int = 1) -> list[Run]:
        """``plan(**request)`` for each request, ``jobs`` datasets collected at a time; requests that share
        datasets are planned one after the other, so that no dataset is written twice at once."""
        by_data: dict[str, list[dict]] = {}
        for request in requests:
            key = f"{request['name']}-{request['preset'].data_key(self.quick)}"
            by_data.setdefault(key, []).append(request)
        threads = 1 if jobs > 1 else 0

        def plan_group(group: list[dict]) -> list[Run]:
            return [run for request in group for run in self.plan(**request, threads=threads)]

        with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
            return [run for runs in pool.map(plan_group, by_data.values()) for run in runs]

    def run_env(self, table: str, name: str, preset: EnvPreset, methods: list[str], seeds: list[int]) -> None:
        self.execute(self.plan(table, name, preset, methods, seeds))

    def execute(self, runs: list[Run], jobs: int = 1) -> None:
        """Train and evaluate ``runs``, ``jobs`` at a time (one CPU thread each when ``jobs`` > 1)."""
        if jobs <= 1:
            for run in runs:
                self._execute(run, threads=0)
            return
        torch.set_num_threads(1)
        # Largest runs first so that the last ones to start are short (longest-processing-time order).
        runs = sorted(runs, key=lambda run: -run.cost)
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            futures = [pool.submit(self._execute, run, 1) for run in runs]
            try:
                for future in as_completed(futures):
                    future.result()
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise

    def _execute(self, run: Run, threads: int) -> None:
        print(f"[benchmark] {run.table} {run.name} {run.method} seed={run.seed}", flush=True)
        preset, episodes = run.preset, self.eval_episodes
        train_seconds, cycles, timing = 0.0, [], {}
        if run.method in ("expert", "random"):
            with self._lock:
                evals = {
                    (lay, None): evaluate_agent(run.method, preset.env_config(lay), episodes)
                    for lay in self.layouts(preset)
                }
        else:
            out = self.work / "runs" / run.table / run.name / f"{run.method}-s{run.seed}"
            shutil.rmtree(out, ignore_errors=True)  # an interrupted, unrecorded run: lerobot-train refuses it
            expert = run.data["expert-actions" if run.method == "bc" else "expert"]
            start = time.perf_counter()
            output = run_cli(
                "lerobot-train", "--policy.type=iupe", f"--dataset.repo_id=local/{expert.name}",
                f"--dataset.root={expert}", "--dataset.video_backend=pyav",
                f"--policy.pre_demos_repo_id=local/{run.data['random'].name}",
                f"--policy.pre_demos_root={run.data['random']}", f"--output_dir={out}", "--policy.device=cpu",
                "--num_workers=0", "--wandb.enable=false", "--save_freq=1000000", "--log_freq=25",
                f"--seed={run.seed}", *run.train_flags,
                log=out.with_suffix(".log"), echo=self.echo, threads=threads,
            )  # fmt: skip
            train_seconds = time.perf_counter() - start
            cycles, timing = read_training_run(out / CHECKPOINT, output, train_steps(run.train_flags))
            evals = {}
            # One evaluation at a time: it seeds the process-wide RNGs, which concurrent evaluations would share.
            with self._lock:
                for lay in self.layouts(preset):
                    for mode in preset.eval_modes:
                        start = time.perf_counter()
                        env_cfg = preset.env_config(lay)
                        evals[lay, mode] = evaluate_checkpoint(out / CHECKPOINT, env_cfg, episodes, mode)
                        timing[f"evaluation_{lay or 'env'}_{mode}_s"] = time.perf_counter() - start
        with self._lock:
            for (lay, mode), overall in evals.items():
                aer = overall["avg_sum_reward"]
                r_expert, r_random = run.references[lay]
                self._save(
                    {
                        "table": run.table, "env": run.name, "method": run.method, "seed": run.seed,
                        "config": run.config_key(episodes), "eval_layouts": lay, "eval_mode": mode,
                        "P": performance([aer], r_expert, r_random), "AER": aer,
                        "success_rate": None if overall["pc_success"] is None else overall["pc_success"] / 100,
                        "train_seconds": train_seconds,
                        "eval_episodes": episodes, "R_expert": r_expert, "R_random": r_random,
                        "timing": timing, "cycles": cycles,
                    }
                )  # fmt: skip


# ---------------------------------------------------------------- report

METHOD_NAMES = {"expert": "Expert", "random": "Random", "bc": "BC", "bco": "BCO(α)", "iupe": "IUPE"}
ENV_NAMES = {"cartpole": "CartPole", "acrobot": "Acrobot", "mountaincar": "MountainCar", "maze3": "Maze 3×3",
             "maze5": "Maze 5×5", "maze10": "Maze 10×10"}  # fmt: skip


def _group(records: list[dict], **match) -> list[dict]:
    return [r for r in records if all(r.get(k) == v for k, v in match.items())]


def _cell(rows: list[dict]) -> str:
    if not rows:
        return "–"
    p, aer = np.array([r["P"] for r in rows]), np.array([r["AER"] for r in rows])
    if len(rows) == 1:
        return f"{p[0]:.3f} / {aer[0]:.3f}"
    return f"{p.mean():.3f} ± {p.std():.3f} / {aer.mean():.3f} ± {aer.std():.3f} (n={len(rows)})"


def _rows(records: list[dict], mode: str | None, **match) -> list[dict]:
    """Rows of a cell; trained methods under evaluation ``mode`` (the built-in agents have none)."""
    if match.get("method") in ("expert", "random"):
        return _group(records, **match)
    return _group(records, eval_mode=mode, **match)


def _table(records, table, envs, methods, layouts, mode, paper=None) -> list[str]:
    head = "| method | " + " | ".join(ENV_NAMES.get(e, e) for e in envs) + " |"
    lines = [head, "|---" * (len(envs) + 1) + "|"]
    for method in methods:
        cells = []
        for env in envs:
            lay = layouts(env)
            cells.append(_cell(_rows(records, mode, table=table, env=env, method=method, eval_layouts=lay)))
        lines.append(f"| {METHOD_NAMES.get(method, method)} (ours) | " + " | ".join(cells) + " |")
        if paper and method in paper:
            ref = paper[method]
            lines.append(
                f"| {METHOD_NAMES.get(method, method)} (paper) | "
                + " | ".join(f"{ref[e][0]:.3f} / {ref[e][1]:.3f}" if e in ref else "–" for e in envs)
                + " |"
            )
    return lines


def _first_rows(records: list[dict]) -> list[dict]:
    """One row per training run (a run has a row per evaluation layout set and mode)."""
    seen, rows = set(), []
    for r in records:
        key = (r["table"], r["env"], r["method"], r["seed"])
        if key not in seen:
            seen.add(key)
            rows.append(r)
    return rows


def write_report(records: list[dict], out: Path, calls: list[dict]) -> list[Path]:
    """results.md, results.json and the PNG plots from all records."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(records, indent=1) + "\n")
    envs1 = [e for e in PRESETS if _group(records, table="table1", env=e)]
    methods = ["expert", "random", "bc", "bco", "iupe"]
    refs = {(r["table"], r["env"], r["eval_layouts"]): (r["R_expert"], r["R_random"]) for r in records}
    lines = [
        "# Benchmark: the paper's Tables 1 and 2 on lerobot_iupe",
        "",
        "Produced on a 2-core CPU, no GPU, by these calls (in order; each resumes from the runs recorded before):",
        "",
        *[
            f"- `{c['command']}` ({c['seconds'] / 60:.1f} min)" + (f": {c['note']}" if "note" in c else "")
            for c in calls
        ],
        "",
        "Cells: P / AER, mean ± std over training seeds "
        "(expert and random rows: the built-in agents, one evaluation). Evaluation: "
        f"{records[0]['eval_episodes'] if records else '?'} episodes on seeds {EVAL_SEED}… never used in training "
        "(mazes: 100 distinct layouts, the demonstration layouts — the paper's protocol — and held-out ones). "
        "Every method of a table is evaluated under the same rule: `argmax` (the policy's most likely action) or "
        "`sample` (a draw from its softmax), `--policy.eval_mode`; every maze checkpoint is evaluated both ways. "
        "The expert and random rows play the built-in agents on the same envs, seeds and layouts with the "
        "package's episode loop (the maze expert reads the simulator's state, which a LeRobot policy cannot).",
        "",
        "References (P = (R − R_random) / (R_expert − R_random)): R_expert = mean return of the expert "
        "demonstrations (held-out maze layouts: of the expert on 100 of them), R_random = uniform-random policy "
        "over 100 episodes (seeds 100000…) on the same layout set:",
        "",
        *[
            f"- {t} {ENV_NAMES.get(e, e)}{f' ({lay} layouts)' if lay else ''}: R_expert {x:.3f}, R_random {y:.3f}"
            for (t, e, lay), (x, y) in refs.items()
        ],
    ]
    findings = out / "findings.md"  # hand-written reading of these numbers, kept beside the report
    if findings.exists():
        lines += ["", findings.read_text().strip()]
    mazes = [e for e in envs1 if e.startswith("maze")]
    demo_layouts = lambda e: "demo" if e.startswith("maze") else None  # noqa: E731
    lines += ["", "## Table 1, argmax evaluation (demonstration layouts for mazes)", ""]
    lines += _table(records, "table1", envs1, methods, demo_layouts, "argmax", PAPER_TABLE1)
    if mazes:
        lines += ["", "## Table 1, mazes, sampled evaluation (demonstration layouts)", ""]
        lines += _table(records, "table1", mazes, methods, demo_layouts, "sample", PAPER_TABLE1)
        for mode in ("argmax", "sample"):
            lines += ["", f"## Table 1, mazes on held-out layouts, {mode} evaluation (not measured in the paper)", ""]
            lines += _table(records, "table1", mazes, methods, lambda e: "heldout", mode)
    if _group(records, table="ablation"):
        lines += ["", "## Table 2: ablation on Maze 10×10 (S = sampling, E = exploration, A = attention on)", ""]
        lines += [
            "| variant | demo layouts, argmax | demo layouts, sample | held-out, argmax | held-out, sample | paper |",
            "|---|---|---|---|---|---|",
        ]
        for variant in ABLATION:
            table = "table1" if variant in ("bco", "iupe") else "ablation"  # the same runs as Table 1's Maze 10×10
            cells = [
                _cell(_group(records, table=table, env="maze10", method=variant, eval_layouts=lay, eval_mode=mode))
                for lay in ("demo", "heldout")
                for mode in ("argmax", "sample")
            ]
            ref = PAPER_TABLE2[variant]
            lines.append(
                f"| {METHOD_NAMES.get(variant, variant)} | {' | '.join(cells)} | {ref[0]:.3f} / {ref[1]:.3f} |"
            )
        lines += [
            "",
            "BCO(α) and IUPE rows: Table 1's Maze 10×10 runs (same datasets, preset and seeds). Cells without n= are "
            "one seed (seed 0): compare them with BCO(α) and IUPE of the same seed in results.json, not with the "
            "3-seed means.",
        ]
    low = [e for e in LOW_DATA if _group(records, table="lowdata", env=e)]
    if low:
        lines += ["", "## Low data: 1 expert episode, ~1,000 pre-demonstration transitions (argmax evaluation)", ""]
        lines += _table(records, "lowdata", low, ["bco", "S", "E", "SE", "iupe"], lambda e: None, "argmax")
    lines += ["", "## Where the time goes (mean seconds per training run)", ""]
    lines += [
        "| table | env | method | runs | train (wall) | rollouts | IDM training | data loading | PM + other | eval |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    trained = [r for r in records if r["seed"] is not None]
    keys = sorted({(r["table"], r["env"], r["method"]) for r in trained}, key=str)
    for table, env, method in keys:
        rows = _first_rows(_group(trained, table=table, env=env, method=method))
        mean = lambda k, rows=rows: float(np.mean([r["timing"].get(k, 0.0) for r in rows]))  # noqa: E731
        train = float(np.mean([r["train_seconds"] for r in rows]))
        evals = float(np.mean([sum(v for k, v in r["timing"].items() if k.startswith("evaluation")) for r in rows]))
        other = train - mean("rollouts_s") - mean("idm_s") - mean("data_loading_s")
        lines.append(
            f"| {table} | {ENV_NAMES.get(env, env)} | {METHOD_NAMES.get(method, method)} | {len(rows)} | {train:.1f} "
            f"| {mean('rollouts_s'):.1f} | {mean('idm_s'):.1f} | {mean('data_loading_s'):.1f} | {other:.1f} "
            f"| {evals:.1f} |"
        )
    for table in sorted({r["table"] for r in trained}):
        rows = _first_rows(_group(trained, table=table))
        train = sum(r["train_seconds"] for r in rows)
        evals = sum(sum(v for k, v in r["timing"].items() if k.startswith("evaluation")) for r in rows)
        lines += ["", f"{table}: {len(rows)} training runs, training {train / 60:.1f} min + evaluation "
                  f"{evals / 60:.1f} min = {(train + evals) / 60:.1f} min."]  # fmt: skip
    wall = sum(c["seconds"] for c in calls) / 60
    lines += ["", f"All calls together: {wall:.1f} min (the sum of their wall-clocks; collection and references "
              "included)."]  # fmt: skip
    plots = plot_results(records, out)
    lines += ["", "## Plots", "", *[f"![{p.stem}]({p.name})" for p in plots]]
    (out / "results.md").write_text("\n".join(lines) + "\n")
    return [out / "results.md", out / "results.json", *plots]


def plot_results(records: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    curves = _first_rows([r for r in records if r["cycles"]])
    groups = sorted({(r["table"], r["env"]) for r in curves}, key=str)
    if groups:
        fig, axes = plt.subplots(2, len(groups), figsize=(4 * len(groups), 6), squeeze=False)
        for col, (table, env) in enumerate(groups):
            for method in sorted({r["method"] for r in _group(curves, table=table, env=env)}, key=str):
                runs = _group(curves, table=table, env=env, method=method)
                n = min(len(r["cycles"]) for r in runs)
                for row, key in enumerate(("success_rate", "return")):
                    values = np.array([[c[key] for c in r["cycles"][:n]] for r in runs])
                    x = np.arange(1, n + 1)
                    axes[row, col].plot(x, values.mean(0), label=METHOD_NAMES.get(method, method))
                    axes[row, col].fill_between(x, values.min(0), values.max(0), alpha=0.2)
            axes[0, col].set_title(f"{ENV_NAMES.get(env, env)} ({table})")
            axes[0, col].set_ylabel("rollout success rate")
            axes[0, col].set_ylim(-0.05, 1.05)
            for ax in axes[:, col]:
                ax.xaxis.get_major_locator().set_params(integer=True)
            axes[1, col].set_ylabel("rollout return (AER)")
            axes[1, col].set_xlabel("cycle")
            axes[0, col].legend(fontsize=7)
        fig.tight_layout()
        paths.append(out / "cycles.png")
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    table1 = [
        r
        for r in records
        if r["table"] == "table1" and r["eval_layouts"] in (None, "demo") and r.get("eval_mode") in (None, "argmax")
    ]
    envs = [e for e in PRESETS if _group(table1, env=e)]
    if envs:
        methods = ["bc", "bco", "iupe"]
        fig, ax = plt.subplots(figsize=(max(6, 2 * len(envs)), 4))
        width = 0.13
        for i, method in enumerate(methods):
            ours = [_group(table1, env=e, method=method) for e in envs]
            mean = [np.mean([r["P"] for r in rows]) if rows else np.nan for rows in ours]
            std = [np.std([r["P"] for r in rows]) if rows else 0 for rows in ours]
            x = np.arange(len(envs)) + (2 * i - 2.5) * width
            ax.bar(x, mean, width, yerr=std, label=f"{METHOD_NAMES[method]} (ours)", color=f"C{i}")
            paper = [PAPER_TABLE1[method][e][0] for e in envs]
            ax.bar(x + width, paper, width, label=f"{METHOD_NAMES[method]} (paper)", color=f"C{i}", alpha=0.4,
                   hatch="//")  # fmt: skip
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_xticks(np.arange(len(envs)), [ENV_NAMES.get(e, e) for e in envs])
        ax.set_ylabel("P (1 = expert, 0 = random)")
        ax.legend(fontsize=7, ncol=3)
        fig.tight_layout()
        paths.append(out / "performance.png")
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    return paths
