"""The benchmark's report: results.md (tables in the paper's layout, one per evaluation rule, references, where the
time goes), results.json, calls.json and the plots, rebuilt from all run records."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from lerobot_iupe.benchmark.evaluation import EVAL_SEED
from lerobot_iupe.benchmark.presets import (
    ABLATION,
    CONTINUOUS,
    LOW_DATA,
    LOW_DATA_CONTINUOUS_METHODS,
    LOW_DATA_METHODS,
    METAWORLD,
    METAWORLD_ANCHORS,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PRESETS,
)

METHOD_NAMES = {
    "expert": "Expert",
    "random": "Random",
    "bc": "BC",
    "bco": "BCO(α)",
    "iupe": "IUPE",
    "ilpo": "ILPO",
    "ilpo_norm": "ILPO + normalize",
}
ENV_NAMES = {"cartpole": "CartPole", "acrobot": "Acrobot", "mountaincar": "MountainCar", "maze3": "Maze 3×3",
             "maze5": "Maze 5×5", "maze10": "Maze 10×10", "lunarlander": "LunarLander",
             "so101_pickplace": "SO-101 pick-and-place",
             "so101_uniform": "SO-101, uniformly random pre-demos",
             **{env: env.removeprefix("mw-") for env in METAWORLD}}  # fmt: skip


MAZE_SELECTION_NOTE = (
    "Mazes, demonstration layouts: the rows are scored on the demonstration layouts that the rollouts — and so "
    "the model selection — never play (rows recording `eval_episodes` 80: the first 80 of the 100; the rollouts "
    "play the last 20, `--policy.rollout_layouts=20`). Maze 3×3 has only 35 distinct mazes among its first 100 "
    "layout ids, so there the rollout layouts repeat evaluated mazes. Rows recording 100 episodes come from "
    "before this split: their checkpoints were selected on the layouts they are scored on."
)
UNRECORDED_SELECTION = (
    "not recorded (rows produced before each row recorded its rule; that code selected as today's: BC its last "
    "weights, the others the cycle with the best rollout success, latest on ties, on rollout seeds ≥ 1,000,000 — "
    "on mazes, the demonstration layouts)"
)


def _group(records: list[dict], **match) -> list[dict]:
    return [r for r in records if all(r.get(k) == v for k, v in match.items())]


def _cell(rows: list[dict]) -> str:
    if not rows:
        return "–"
    p, aer = np.array([r["P"] for r in rows]), np.array([r["AER"] for r in rows])
    if len(rows) == 1:
        return f"{p[0]:.3f} / {aer[0]:.3f}"
    return f"{p.mean():.3f} ± {p.std(ddof=1):.3f} / {aer.mean():.3f} ± {aer.std(ddof=1):.3f} (n={len(rows)})"


def _rows(records: list[dict], mode: str | None, **match) -> list[dict]:
    """Rows of a cell; trained methods under evaluation ``mode`` (the built-in agents have none)."""
    if match.get("method") in ("expert", "random"):
        return _group(records, **match)
    return _group(records, eval_mode=mode, **match)


def _success_cell(rows: list[dict]) -> str:
    rates = np.array([r["success_rate"] for r in rows if r.get("success_rate") is not None])
    if not len(rates):
        return "–"
    return f"{rates[0]:.2f}" if len(rates) == 1 else f"{rates.mean():.2f} ± {rates.std(ddof=1):.2f} (n={len(rates)})"


def _table(records, table, envs, methods, layouts, mode, paper=None, cell=_cell) -> list[str]:
    head = "| method | " + " | ".join(ENV_NAMES.get(e, e) for e in envs) + " |"
    lines = [head, "|---" * (len(envs) + 1) + "|"]
    for method in methods:
        cells = []
        for env in envs:
            lay = layouts(env)
            cells.append(cell(_rows(records, mode, table=table, env=env, method=method, eval_layouts=lay)))
        if all(c == "–" for c in cells) and not (paper and method in paper):
            continue  # a method this table never ran
        lines.append(f"| {METHOD_NAMES.get(method, method)} (ours) | " + " | ".join(cells) + " |")
        if paper and method in paper:
            ref = paper[method]
            lines.append(
                f"| {METHOD_NAMES.get(method, method)} (paper) | "
                + " | ".join(f"{ref[e][0]:.3f} / {ref[e][1]:.3f}" if e in ref else "–" for e in envs)
                + " |"
            )
    return lines


REPRODUCE = {
    table: f"lerobot-iupe-benchmark --tables {table} --jobs 2"
    for table in ("table1", "ablation", "continuous", "lowdata")
}


def metaworld_section(records: list[dict], methods: list[str]) -> list[str]:
    """Meta-World's success rates (%, by the mode) per task and their mean, with other papers' figures below."""
    envs = [e for e in METAWORLD if _group(records, table="metaworld", env=e)]
    if not envs:  # no section, and no mean over an empty list
        return []
    tasks, methods = [ENV_NAMES[e] for e in envs], [m for m in methods if _group(records, table="metaworld", method=m)]
    lines = [
        "", "## Meta-World (state: the 39 values), success rate % by the mode (lerobot-eval's rule)", "",
        "Mean ± sample standard deviation over training seeds (n = seeds). 10 scripted-expert demonstrations per "
        "task; BC learns from their true actions, BCO(α), IUPE and ILPO from their states alone. Reproduce: "
        f"`lerobot-iupe-benchmark --tables metaworld --envs {' '.join(envs)} --methods {' '.join(methods)} "
        "--eval_episodes 50 --jobs 2 --work outputs/metaworld --out benchmarks/metaworld`",
        "", "| method | " + " | ".join(tasks) + " | mean |", "|---" * (len(tasks) + 2) + "|",
    ]  # fmt: skip
    for method in methods:
        per_task = [
            [100 * r["success_rate"] for r in _rows(records, "argmax", table="metaworld", env=e, method=method)]
            for e in envs
        ]
        cells = [
            "–" if not rates else f"{rates[0]:.0f}" if len(rates) == 1 else
            f"{np.mean(rates):.0f} ± {np.std(rates, ddof=1):.0f} (n={len(rates)})"
            for rates in per_task
        ]  # fmt: skip
        mean = f"{np.mean([np.mean(r) for r in per_task]):.1f}" if all(per_task) else "–"
        if any(per_task):  # a method never run has no row
            lines.append(f"| {METHOD_NAMES.get(method, method)} (ours) | " + " | ".join(cells) + f" | {mean} |")
    for name, rates in METAWORLD_ANCHORS.items():
        cells = [str(rates[t]) for t in tasks] + [f"{np.mean([rates[t] for t in tasks]):.1f}"]
        lines.append(f"| {name} (other paper's protocol) | " + " | ".join(cells) + " |")
    note = (
        "Other papers' rows: the 3D Diffusion Policy paper (Ze et al., 2024, Table XVIII), 10 demonstrations, with "
        "the expert's actions, from point clouds (DP3) or images, the mean of its 5 best evaluations: not this "
        "protocol, shown for scale."
    )
    return [*lines, "", note]


def env_steps_table(records: list[dict]) -> list[str]:
    """Mean env steps per training run, by what took them (rows record ``env_steps`` since the counts exist)."""
    lines = ["", "## Env steps used in training (mean per run)", ""]
    lines += [
        "Every step any method took in an env to train or to choose its checkpoint: the pre-demonstrations it learned "
        "from (BCO(α), IUPE), its own play (IUPE's rollouts, ILPO's remapping) and the episodes played only to select "
        "the model. The expert demonstrations and the evaluation are not counted. Runs recorded before the counts "
        "existed read 'not recorded'.",
        "",
        "| table | env | method | runs | pre-demonstrations | rollouts / remapping | selection episodes | total |",
        "|---|---|---|---|---|---|---|---|",
    ]
    trained = [r for r in _first_rows(records) if r["seed"] is not None]
    for table, env, method in sorted({(r["table"], r["env"], r["method"]) for r in trained}, key=str):
        rows = _group(trained, table=table, env=env, method=method)
        counted = [r["env_steps"] for r in rows if r.get("env_steps")]
        name = f"| {table} | {ENV_NAMES.get(env, env)} | {METHOD_NAMES.get(method, method)} | {len(rows)} |"
        if len(counted) < len(rows):
            lines.append(f"{name} not recorded | | | |")
            continue
        mean = {k: float(np.mean([c[k] for c in counted])) for k in counted[0]}
        total = sum(mean.values())
        lines.append(
            f"{name} {mean['pre_demonstrations']:,.0f} | {mean['online']:,.0f} | {mean['selection']:,.0f} "
            f"| {total:,.0f} |"
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
    (out / "calls.json").write_text(json.dumps(calls, indent=1) + "\n")
    envs1 = [e for e in PRESETS if _group(records, table="table1", env=e)]
    methods = ["expert", "random", "bc", "bco", "iupe", "ilpo", "ilpo_norm"]
    refs = {(r["table"], r["env"], r["eval_layouts"]): (r["R_expert"], r["R_random"]) for r in records}
    lines = [
        "# Benchmark: the paper's Tables 1 and 2 on lerobot_iupe",
        "",
        "Produced on a 2-core CPU, no GPU, by `lerobot-iupe-benchmark` (each table names the call that reproduces "
        "it; every call that produced these records is listed at the end and in calls.json).",
        "",
        "Cells: P / AER, mean ± sample standard deviation (ddof = 1) over training seeds "
        "(expert and random rows: the built-in agents, one evaluation). Evaluation: "
        f"{records[0]['eval_episodes'] if records else '?'} episodes on seeds {EVAL_SEED}… never used in training "
        "(mazes: 100 distinct layouts, the demonstration layouts — the paper's protocol — and held-out ones). "
        "Every method of a table is evaluated under the same rule: `argmax` (the policy's most likely action) or "
        "`sample` (a draw from its softmax or Gaussian), `--policy.eval_mode`; every checkpoint is evaluated both "
        "ways (`argmax` is what `lerobot-eval` plays by default). "
        "The expert and random rows play the built-in agents on the same envs, seeds and layouts with the "
        "package's episode loop (the maze expert reads the simulator's state, which a LeRobot policy cannot).",
        "",
        "References (P = (R − R_random) / (R_expert − R_random)): R_expert and R_random are the mean returns of the "
        "built-in expert and of the uniform-random agent on exactly the episodes the rows are scored on (the same "
        "seeds and layouts), so the Random row scores P = 0 and the Expert row P = 1 by construction, and every "
        "table of an env (low data included) shares one reference:",
        "",
        *[
            f"- {t} {ENV_NAMES.get(e, e)}{f' ({lay} layouts)' if lay else ''}: R_expert {x:.3f}, R_random {y:.3f}"
            for (t, e, lay), (x, y) in refs.items()
        ],
    ]
    if (out / "findings.md").exists():  # the hand-written, dated reading of these numbers, kept beside the report
        lines += ["", "What these numbers say, dated, with what each finding decided: [findings.md](findings.md)."]
    mazes = [e for e in envs1 if e.startswith("maze")]
    demo_layouts = lambda e: "demo" if e.startswith("maze") else None  # noqa: E731
    for mode in ("argmax", "sample") if envs1 else ():
        lines += ["", f"## Table 1, {mode} evaluation (demonstration layouts for mazes)", ""]
        lines += [f"Reproduce: `{REPRODUCE['table1']}`", ""]
        lines += _table(records, "table1", envs1, methods, demo_layouts, mode, PAPER_TABLE1)
        if mazes:
            lines += ["", MAZE_SELECTION_NOTE]
    if mazes:
        for mode in ("argmax", "sample"):
            lines += ["", f"## Table 1, mazes on held-out layouts, {mode} evaluation (not measured in the paper)", ""]
            lines += _table(records, "table1", mazes, methods, lambda e: "heldout", mode)
    if _group(records, table="ablation"):
        lines += ["", "## Table 2: ablation on Maze 10×10 (S = sampling, E = exploration, A = attention on)", ""]
        lines += [f"Reproduce: `{REPRODUCE['ablation']}`", ""]
        lines += [
            "| variant | demo layouts, argmax | demo layouts, sample | held-out, argmax | held-out, sample | paper |",
            "|---|---|---|---|---|---|",
        ]
        one_seed = False
        for variant in ABLATION:
            table = "table1" if variant in ("bco", "iupe") else "ablation"  # the same runs as Table 1's Maze 10×10
            one_seed |= len(_group(records, table=table, env="maze10", method=variant, eval_mode="argmax")) == 2
            cells = [
                _cell(_group(records, table=table, env="maze10", method=variant, eval_layouts=lay, eval_mode=mode))
                for lay in ("demo", "heldout")
                for mode in ("argmax", "sample")
            ]
            ref = PAPER_TABLE2[variant]
            lines.append(
                f"| {METHOD_NAMES.get(variant, variant)} | {' | '.join(cells)} | {ref[0]:.3f} / {ref[1]:.3f} |"
            )
        note = "BCO(α) and IUPE rows: Table 1's Maze 10×10 runs (same datasets, preset and seeds)."
        demo_episodes = lambda table: {  # noqa: E731
            r["eval_episodes"] for r in _group(records, table=table, env="maze10", eval_layouts="demo")
        }
        if demo_episodes("ablation") and demo_episodes("ablation") != demo_episodes("table1"):
            note += (
                f" **Not comparable row to row:** the variants' demonstration-layout cells were evaluated on "
                f"{sorted(demo_episodes('ablation'))} episodes and Table 1's on {sorted(demo_episodes('table1'))}: "
                "they were trained under different model-selection splits (see Table 1's note), and the variants "
                "have not been run again since."
            )
        if one_seed:  # a training run has two argmax rows: demonstration and held-out layouts
            note += (
                " Cells without n= are one seed: compare them with BCO(α) and IUPE of the same seed in "
                "results.json, not with the 3-seed means."
            )
        lines += ["", note]
    continuous = [e for e in CONTINUOUS if _group(records, table="continuous", env=e)]
    if continuous:
        for mode, rule in (("argmax", "the Gaussian's mode"), ("sample", "a draw from the Gaussian")):
            lines += ["", f"## Continuous actions, {mode} evaluation ({rule}): P / AER", ""]
            lines += [f"Reproduce: `{REPRODUCE['continuous']}`", ""]
            lines += _table(records, "continuous", continuous, methods, lambda e: None, mode)
            lines += ["", f"Success rate (LeRobot's `is_success`), {mode} evaluation, mean ± std over seeds:", ""]
            lines += _table(records, "continuous", continuous, methods, lambda e: None, mode, cell=_success_cell)
    low = [e for e in LOW_DATA if _group(records, table="lowdata", env=e)]
    if low:
        for mode in ("argmax", "sample"):
            lines += [
                "",
                f"## Low data: 1 expert episode, ~1,000 pre-demonstration transitions ({mode} evaluation)",
                "",
                f"Reproduce: `{REPRODUCE['lowdata']}`",
                "",
            ]
            lines += _table(records, "lowdata", low, LOW_DATA_METHODS, lambda e: None, mode)
        if any(e in CONTINUOUS for e in low):
            lines += ["", f"Continuous envs' low-data rows: {', '.join(LOW_DATA_CONTINUOUS_METHODS)} only."]
    lines += metaworld_section(records, methods)
    lines += env_steps_table(records)
    lines += ["", "## How each checkpoint was selected (the rule each row records)", ""]
    by_rule: dict[str, list[str]] = {}
    for r in _first_rows([r for r in records if r["seed"] is not None]):
        rule = r.get("selection", UNRECORDED_SELECTION)
        row = f"{r['table']} {ENV_NAMES.get(r['env'], r['env'])} {METHOD_NAMES.get(r['method'], r['method'])}"
        if row not in by_rule.setdefault(rule, []):
            by_rule[rule].append(row)
    lines += [f"- {rule}: {', '.join(rows)}" for rule, rows in sorted(by_rule.items())]
    lines += ["", "## Where the time goes (mean seconds per training run)", ""]
    lines += [
        "| table | env | method | runs | train (wall) | rollouts | selection episodes | IDM training | data loading "
        "| PM + other | eval |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    trained = [r for r in records if r["seed"] is not None]
    keys = sorted({(r["table"], r["env"], r["method"]) for r in trained}, key=str)
    for table, env, method in keys:
        rows = _first_rows(_group(trained, table=table, env=env, method=method))
        mean = lambda k, rows=rows: float(np.mean([r["timing"].get(k, 0.0) for r in rows]))  # noqa: E731
        train = float(np.mean([r["train_seconds"] for r in rows]))
        evals = float(np.mean([sum(v for k, v in r["timing"].items() if k.startswith("evaluation")) for r in rows]))
        other = train - mean("rollouts_s") - mean("selection_s") - mean("idm_s") - mean("data_loading_s")
        lines.append(
            f"| {table} | {ENV_NAMES.get(env, env)} | {METHOD_NAMES.get(method, method)} | {len(rows)} | {train:.1f} "
            f"| {mean('rollouts_s'):.1f} | {mean('selection_s'):.1f} | {mean('idm_s'):.1f} "
            f"| {mean('data_loading_s'):.1f} | {other:.1f} | {evals:.1f} |"
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
    lines += ["", "## The calls that produced these records (in order; each resumed from the runs before it)", ""]
    lines += [f"- `{c['command']}` ({c['seconds'] / 60:.1f} min)" for c in calls]
    lines += ["", "What each call ran, and on what it shared the CPU: calls.json (`note`)."]
    (out / "results.md").write_text("\n".join(lines) + "\n")
    return [out / "results.md", out / "results.json", out / "calls.json", *plots]


def plot_results(records: list[dict], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    # rollout curves: a supervised run's cycles record its selection episodes only (it plays no rollouts)
    curves = _first_rows([r for r in records if r["cycles"] and "success_rate" in r["cycles"][0]])
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
        methods = ["bc", "bco", "iupe", "ilpo"]
        fig, ax = plt.subplots(figsize=(max(6, 2.5 * len(envs)), 4))
        width = 0.1
        for i, method in enumerate(methods):
            ours = [_group(table1, env=e, method=method) for e in envs]
            mean = [np.mean([r["P"] for r in rows]) if rows else np.nan for rows in ours]
            std = [np.std([r["P"] for r in rows], ddof=1) if len(rows) > 1 else 0 for rows in ours]
            x = np.arange(len(envs)) + (2 * i - 3.5) * width
            ax.bar(x, mean, width, yerr=std, label=f"{METHOD_NAMES[method]} (ours)", color=f"C{i}")
            paper = [PAPER_TABLE1[method][e][0] for e in envs]
            ax.bar(x + width, paper, width, label=f"{METHOD_NAMES[method]} (paper)", color=f"C{i}", alpha=0.4,
                   hatch="//")  # fmt: skip
        ax.axhline(1.0, color="k", lw=0.8, ls="--")
        ax.set_xticks(np.arange(len(envs)), [ENV_NAMES.get(e, e) for e in envs])
        ax.set_ylabel("P (1 = expert, 0 = random)")
        ax.legend(fontsize=7, ncol=4)
        fig.tight_layout()
        paths.append(out / "performance.png")
        fig.savefig(paths[-1], dpi=90)
        plt.close(fig)
    return paths
