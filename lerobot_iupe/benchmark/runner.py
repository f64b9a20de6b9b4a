"""The benchmark's runner: the paper's Tables 1 and 2 on this package — Expert, Random, BC, BCO(α) and IUPE (and
the ablation variants), each trained through ``lerobot-train`` and evaluated with LeRobot's own evaluation code
(``eval_policy_all``, what ``lerobot-eval`` runs, without its video rendering).

Every finished run is appended to ``<work>/runs.jsonl`` at once, so an interrupted benchmark resumes where it
stopped; the report (``report.py``) is rebuilt from all records on every call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm.auto import tqdm

from lerobot_iupe.benchmark.evaluation import evaluate_agent, evaluate_checkpoint, read_training_run
from lerobot_iupe.benchmark.presets import QUICK_BUDGET, EnvPreset, digest, policy_type
from lerobot_iupe.benchmark.runs import Run, agent_config_key, selection_rule, training_env_steps
from lerobot_iupe.policy.algorithm import performance

BIN = Path(sys.executable).parent
CHECKPOINT = "checkpoints/last/pretrained_model"


STEP = re.compile(r"\bstep:(\d+(?:\.\d+)?)([KM]?)\b")


def run_cli(
    *args: str, log: Path | None = None, quiet: bool = False, steps: int = 0, threads: int = 0, label: str = ""
) -> str:
    """Run a console script; its output is returned and written to ``log``. By default its command line is printed;
    with ``quiet`` nothing is printed but, when ``steps`` > 0, a progress bar over lerobot-train's logged steps.
    ``threads`` > 0 caps its CPU threads (OMP_NUM_THREADS)."""
    if not quiet:
        print("$", shlex.join(args), flush=True)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)} if threads else None
    process = subprocess.Popen(
        [str(BIN / args[0]), *args[1:]], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    bar = tqdm(total=steps, desc=label or args[0], unit="step", disable=not (quiet and steps), leave=True)
    lines = []
    for line in process.stdout:
        lines.append(line)
        if match := STEP.search(line):
            value = float(match.group(1)) * {"": 1, "K": 1_000, "M": 1_000_000}[match.group(2)]
            bar.update(int(value) - bar.n)
    output = "".join(lines)
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(output)
    if process.wait() != 0:
        bar.close()
        raise RuntimeError(f"{args[0]} failed ({process.returncode}); see {log}\n{output[-2000:]}")
    bar.update(bar.total - bar.n)
    bar.close()
    return output


def collect_datasets(
    name: str,
    preset: EnvPreset,
    data_dir: Path,
    quick: bool = False,
    threads: int = 0,
    quiet: bool = False,
    with_actions: bool = True,
) -> dict[str, Path]:
    """Expert (state only), the same expert episodes with actions (for BC; ``with_actions``), random
    pre-demonstrations."""
    paths = {}
    n_expert, n_random = preset.data.expert_episodes, preset.data.random_episodes
    if quick:
        n_expert, n_random = min(n_expert, 5), min(n_random, 60)
    expert = (preset.data_key(quick), preset.env_flags())
    pre_demos = (preset.pre_demos_key(quick), preset.pre_demos_flags())
    for kind, agent, episodes, (key, env_flags), extra in [
        ("expert", "expert", n_expert, expert, ["--seed=0"]),
        ("expert-actions", "expert", n_expert, expert, ["--seed=0", "--keep_actions=true"]),
        ("random", preset.data.pre_demos_agent, n_random, pre_demos, ["--seed=1000", *preset.data.random_flags()]),
    ]:
        if kind == "expert-actions" and not with_actions:
            continue
        root = data_dir / f"{name}-{key}-{kind}"
        if not (root / "meta" / "iupe.json").exists():
            run_cli(
                "lerobot-iupe-collect", *env_flags, f"--agent={agent}", f"--episodes={episodes}", *extra,
                *preset.data.data_flags(),
                f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", "--overwrite=true",
                threads=threads, quiet=quiet, log=data_dir / "logs" / f"{root.name}.log",
            )  # fmt: skip
        paths[kind] = root
    return paths


@dataclass
class Benchmark:
    work: Path
    eval_episodes: int = 100
    quick: bool = False
    quiet: bool = False  # the demo: progress bars instead of command lines; every output is in a log file
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    _agents: dict[str, dict] = field(default_factory=dict, repr=False)  # built-in agents' evaluations, by key

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

    def seed_from(self, results_dir: Path) -> int:
        """Add the records of a committed report (``results.json``, and its calls from ``calls.json``) to this work
        folder, so a call resumes from published runs instead of training them again. Returns how many records
        were new; a record already present (same fields) is not added twice."""
        known = {json.dumps(r, sort_keys=True) for r in self.records()}
        published = json.loads((results_dir / "results.json").read_text())
        new = [r for r in published if json.dumps(r, sort_keys=True) not in known]
        for record in new:
            self._save(record)
        calls = results_dir / "calls.json"
        if calls.exists() and not self.calls_file.exists():
            self.calls_file.write_text("".join(json.dumps(c) + "\n" for c in json.loads(calls.read_text())))
        return len(new)

    def forget(self, runs: list[tuple[str, str, str, int | None]], unless_config: dict | None = None) -> int:
        """Drop the records of ``runs`` (table, env, method, seed) from ``runs.jsonl``, except those whose
        configuration key is ``unless_config[run]``; returns how many rows went. The file is replaced whole
        (written beside it, then renamed), so an interruption loses nothing."""
        keep, dropped, runs, unless_config = [], 0, set(runs), unless_config or {}
        for record in self.records():
            run = (record["table"], record["env"], record["method"], record["seed"])
            if run in runs and record.get("config") != unless_config.get(run):
                dropped += 1
            else:
                keep.append(record)
        if dropped:
            self._rewrite(keep)
        return dropped

    def _rewrite(self, records: list[dict]) -> None:
        """Replace ``runs.jsonl`` whole (written beside it, then renamed), so an interruption loses nothing."""
        partial = self.records_file.with_suffix(".jsonl.partial")
        partial.write_text("".join(json.dumps(r) + "\n" for r in records))
        partial.replace(self.records_file)

    def _save(self, record: dict) -> None:
        self.work.mkdir(parents=True, exist_ok=True)
        with self.records_file.open("a") as f:
            f.write(json.dumps(record) + "\n")

    def _done(self, run: Run) -> bool:
        key = (run.table, run.name, run.method, run.seed, run.config_key(self.eval_episodes))
        return any((r["table"], r["env"], r["method"], r["seed"], r.get("config")) == key for r in self.records())

    def agent_evaluation(self, agent: str, preset: EnvPreset, layouts: str | None) -> dict:
        """A built-in agent on the scored episodes of ``preset`` (evaluated once per env, layouts and episode
        count: every table of an env shares it). A recorded row of the agent with the configuration key its row
        would have (a resumed call, or a report added by --from) is that evaluation: it is read, not played again,
        as a recorded run is not trained again (``--rerun --methods expert random`` plays them anew)."""
        episodes = preset.scored_episodes(layouts, self.eval_episodes)
        env_cfg = preset.env_config(layouts)
        key = digest([agent, repr(env_cfg), episodes])
        with self._lock:
            if key in self._agents:
                return self._agents[key]
            recorded = self._recorded_agent_evaluation(agent, preset, layouts)
        overall = recorded or evaluate_agent(agent, env_cfg, episodes)
        with self._lock:
            return self._agents.setdefault(key, overall)

    def _recorded_agent_evaluation(self, agent: str, preset: EnvPreset, layouts: str | None) -> dict | None:
        """What ``evaluate_agent`` returned for the recorded row of ``agent`` on these episodes, if there is one."""
        config = agent_config_key(preset, self.quick, self.eval_episodes)
        for record in self.records():
            if (record["method"], record.get("config"), record["eval_layouts"]) == (agent, config, layouts):
                success = record["success_rate"]
                return {"avg_sum_reward": record["AER"], "pc_success": None if success is None else 100.0 * success}
        return None

    def references(self, preset: EnvPreset) -> dict[str | None, tuple[float, float]]:
        """Per evaluation layout set: (R_expert, R_random), the mean returns of the built-in expert and of the
        uniform-random agent on exactly the episodes every row is scored on (seeds ``EVAL_SEED``…, the same
        layouts), so that the Random row scores P = 0 and the Expert row P = 1 by construction, and one reference
        serves every table of an env (low data included)."""
        return {
            layouts: tuple(
                float(self.agent_evaluation(agent, preset, layouts)["avg_sum_reward"]) for agent in ("expert", "random")
            )
            for layouts in preset.layouts
        }

    def rescore(
        self, table: str, name: str, preset: EnvPreset, references: dict[str | None, tuple[float, float]]
    ) -> int:
        """Score the recorded rows of ``table``/``name`` against ``references`` (P from each row's own AER), where
        they were scored against others on the same episodes; returns how many rows changed. A row evaluated on
        other episodes (an older layout split) keeps its own. Rewritten whole, as ``forget``."""
        records, changed = self.records(), 0
        for record in records:
            if (record["table"], record["env"]) != (table, name) or record["eval_layouts"] not in references:
                continue
            if record["eval_episodes"] != preset.scored_episodes(record["eval_layouts"], self.eval_episodes):
                continue
            r_expert, r_random = references[record["eval_layouts"]]
            if (record["R_expert"], record["R_random"]) != (r_expert, r_random):
                record.update(R_expert=r_expert, R_random=r_random, P=performance([record["AER"]], r_expert, r_random))
                changed += 1
        if changed:
            self._rewrite(records)
        return changed

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
        seed and configuration key exists), after measuring the references (and scoring recorded rows against
        them); the datasets are collected where a run to train needs them."""
        if self.quick:  # one budget for training and evaluation settings alike (no layout split in a smoke test)
            preset = dataclasses.replace(preset, train=QUICK_BUDGET)
        references = self.references(preset)
        with self._lock:
            self.rescore(table, name, preset, references)
        runs = [
            Run(table, name, preset, method, seed, {}, references, self.quick)
            for method in methods
            for seed in ([None] if method in ("expert", "random") else seeds)
        ]
        pending = [run for run in runs if not self._done(run)]
        # Rows of another configuration of a planned run (an older one, or one --from added back beside a newer
        # run) are replaced by the run's own, never kept beside them.
        current = {(run.table, run.name, run.method, run.seed): run.config_key(self.eval_episodes) for run in runs}
        with self._lock:
            self.forget(list(current), unless_config=current)
        if any(run.method not in ("expert", "random") for run in pending):  # the built-in agents need no data
            data = collect_datasets(name, preset, self.work / "data", self.quick, threads, self.quiet, "bc" in methods)
            for run in pending:
                run.data = data
        return pending

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

    @contextlib.contextmanager
    def _output_to(self, log: Path) -> Iterator[None]:
        """Quiet: what LeRobot's evaluation prints (its progress bars, weight loading) goes to ``log``."""
        if not self.quiet:
            yield
            return
        with log.open("w") as file, contextlib.redirect_stdout(file), contextlib.redirect_stderr(file):
            yield

    def _execute(self, run: Run, threads: int) -> None:
        if not self.quiet:
            print(f"[benchmark] {run.table} {run.name} {run.method} seed={run.seed}", flush=True)
        preset, episodes = run.preset, self.eval_episodes
        train_seconds, cycles, timing, env_steps = 0.0, [], {}, None
        selection = "none: the built-in agent"
        if run.method in ("expert", "random"):
            evals = {(lay, None): self.agent_evaluation(run.method, preset, lay) for lay in preset.layouts}
        else:
            out = self.work / "runs" / run.table / run.name / f"{run.method}-s{run.seed}"
            shutil.rmtree(out, ignore_errors=True)  # an interrupted, unrecorded run: lerobot-train refuses it
            expert = run.data["expert-actions" if run.method == "bc" else "expert"]
            pre_demos = [] if policy_type(run.method) == "ilpo" else [  # ILPO learns from the expert's states alone
                f"--policy.pre_demos_repo_id=local/{run.data['random'].name}",
                f"--policy.pre_demos_root={run.data['random']}",
            ]  # fmt: skip
            start = time.perf_counter()
            output = run_cli(
                "lerobot-train", f"--policy.type={policy_type(run.method)}", f"--dataset.repo_id=local/{expert.name}",
                f"--dataset.root={expert}", "--dataset.video_backend=pyav", *pre_demos,
                f"--output_dir={out}", "--policy.device=cpu",
                "--num_workers=0", "--wandb.enable=false", "--save_freq=1000000", "--log_freq=25",
                f"--seed={run.seed}", *run.train_flags, f"--steps={run.steps}",
                log=out.with_suffix(".log"), quiet=self.quiet, threads=threads,
                steps=run.steps, label=f"train {run.method} {run.name} seed {run.seed}",
            )  # fmt: skip
            train_seconds = time.perf_counter() - start
            cycles, timing = read_training_run(out / CHECKPOINT, output, run.steps)
            env_steps = training_env_steps(run, out / CHECKPOINT, cycles)
            selection = selection_rule(run, out / CHECKPOINT, cycles)
            evals = {}
            # One evaluation at a time: it seeds the process-wide RNGs, which concurrent evaluations would share.
            with self._lock, self._output_to(out.with_suffix(".eval.log")):
                for lay in preset.layouts:
                    for mode in preset.eval_modes:
                        start = time.perf_counter()
                        env_cfg, n = preset.env_config(lay), preset.scored_episodes(lay, episodes)
                        evals[lay, mode] = evaluate_checkpoint(out / CHECKPOINT, env_cfg, n, mode)
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
                        "selection": selection, "train_seconds": train_seconds,
                        "eval_episodes": preset.scored_episodes(lay, episodes), "R_expert": r_expert,
                        "R_random": r_random,
                        "timing": timing, "cycles": cycles, "env_steps": env_steps,
                    }
                )  # fmt: skip
