"""benchmarks/relabel.json and its rendering benchmarks/relabel.md, shared by the relabelling measurements
(relabel.py, downstream.py, context.py): each writes its own sections and the command that
produced them, and the page is rendered from the whole file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

# (a)'s success rate below which the ratio (b) / (a) is no result: a policy that fails most episodes on the true
# actions has not learned the task, so labels cannot be judged by it (the target asks for true arms of 0.5 or more)
MEASURABLE = 0.5


def load(out: Path) -> dict:
    path = out / "relabel.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data.setdefault("commands", {})
    return data


def update(out: Path, section: str, rows: list[dict], command: str, key: tuple[str, ...] | None = None) -> None:
    """Put ``rows`` into ``section``, replacing rows with the same ``key`` values (all of them when no key)."""
    data = load(out)
    if key is None:
        data[section] = rows
    else:
        of = lambda r: tuple(json.dumps(r.get(k)) for k in key)  # noqa: E731  (lists are keys too)
        new = {of(r) for r in rows}
        data[section] = [r for r in data.get(section, []) if of(r) not in new] + rows
    commands = data["commands"].get(section, [])
    commands = [commands] if isinstance(commands, str) else commands
    data["commands"][section] = commands + [command] if command not in commands else commands
    out.mkdir(parents=True, exist_ok=True)
    (out / "relabel.json").write_text(json.dumps(data, indent=2) + "\n")
    (out / "relabel.md").write_text(render(out))


def _commands(data: dict, section: str) -> str:
    commands = data["commands"].get(section, [])
    return ", ".join(f"`{c}`" for c in ([commands] if isinstance(commands, str) else commands))


def _labels(row: dict) -> str:
    if row["labels"] == "true":
        return "true"
    if row.get("idm_context") is None:
        return "idm"
    pulled = f", pulled {row['pull_to_observation']:g}σ" if row.get("pull_to_observation") else ""
    return f"idm (k={row['idm_context']}{pulled})"


def _policy(row: dict) -> str:
    """The row's policy and how it was set: ``act chunk10``, ``diffusion lerobot``."""
    return f"{row.get('policy', 'act')} {row['act']}"


def _f(x: float | None, digits: int = 3) -> str:
    return "–" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.{digits}f}"


def _fit(rows: list[dict]) -> str:
    fits = [r["training_fit_r2_per_dim"] for r in rows if r.get("training_fit_r2_per_dim")]
    return ", ".join(f"{x:.2f}" for x in np.mean(fits, axis=0)) if fits else "–"


def _seconds(rows: list[dict], key: str) -> str:
    """The runs' mean seconds of ``key`` (– where a row does not record it); training resumed from a shorter run
    says so, as its seconds count only the steps after that run's."""
    values = [r[key] for r in rows if r.get(key) is not None]
    if len(values) != len(rows):
        return "–"
    resumed = [r.get("resumed_from_steps") for r in rows]
    if key != "train_s" or not any(resumed):
        return f"{np.mean(values):.0f}"
    if len(set(resumed)) == 1:
        return f"{np.mean(values):.0f} (after step {resumed[0]})"
    # runs resumed from different steps (or some from scratch) do not average: each is given
    return ", ".join(f"{v:.0f}" + (f" (after step {r})" if r else "") for v, r in zip(values, resumed, strict=True))


def _real_cameras(data: dict) -> list[str]:
    """Targets: held-out R² ≥ 0.95 per joint, relabel ≥ 0.8× the plain decode rate, peak memory ≤ 4 GB."""
    lines = [
        "## Real camera data: two 640×480 cameras, 2,000 and 20,000 frames",
        "",
        _commands(data, "real_cameras"),
        "",
        "An SO-101-shaped recording written by LeRobot's own writer (`lerobot_iupe.data.arm_recording`: two 640×480 "
        "AV1 cameras that show a six-joint arm, joint positions in degrees, the leader's absolute joint targets as "
        "actions, 30 fps, episodes of 250 frames). A supervised IDM is trained on it by `lerobot-train` with default "
        "flags (working resolution 96×128, batch 8, 4 loader workers) and scored by `lerobot-iupe-relabel "
        "--dry_run=true` on 10 held-out episodes. Relabelling reads the training recording; the plain decode rate "
        "is one process and one thread decoding both cameras' videos whole at full size with the same decoder. "
        "Peak memory is the largest resident set of any process of the command (`/usr/bin/time`); *allocated* is "
        "its anonymous part, sampled every 0.2 s: resident memory without the file pages of the memory-mapped "
        "frame cache.",
        "",
        "| frames | steps | train steps/s | train peak (allocated) GB | held-out R² per joint (min) "
        "| decoder | relabel frames/s | plain decode frames/s | ratio | relabel peak (allocated) GB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in data["real_cameras"]:
        r2 = r["held_out_r2"]
        scores = f"{', '.join(f'{v:.3f}' for v in r2.values())} ({min(r2.values()):.3f})"
        for backend in ("torchcodec", "pyav"):
            b = r[backend]
            lines.append(
                f"| {r['frames']} | {r['steps']} | {r['train_steps_per_s']:.1f} | {r['train_peak_rss_gb']:.2f} "
                f"({r['train_peak_anon_gb']:.2f}) | {scores} | {backend} | {b['relabel_frames_per_s']:.0f} "
                f"| {b['decode_frames_per_s']:.0f} | {b['ratio']:.2f} | {b['relabel_peak_rss_gb']:.2f} "
                f"({b['relabel_peak_anon_gb']:.2f}) |"
            )
    if data.get("real_cameras_findings"):
        lines += ["", "### Reading", "", *[f"- {f}" for f in data["real_cameras_findings"]]]
    return lines + [""]


def render(out: Path) -> str:
    data = load(out)
    lines = ["# lerobot-iupe-relabel: measured", "", "On a 2-core CPU, no GPU. Every section names its command.", ""]
    if data.get("arm_idm_markdown"):  # written by arm_idm.py's runs and kept as text
        lines += [data["arm_idm_markdown"], ""]
    if data.get("real_cameras"):
        lines += _real_cameras(data)
    if data.get("resolution"):
        lines += [
            "### The working resolution for 640×480 cameras",
            "",
            _commands(data, "resolution"),
            "",
            "| resolution | IDM reads | steps | held-out R² per joint | min | train steps/s "
            "| relabel frames/s (torchcodec) |",
            "|---|---|---|---|---|---|---|",
            *[
                f"| {r['shape'][0]}×{r['shape'][1]} | {r.get('idm_reads', 'cameras and state')} | {r['steps']} "
                f"| {', '.join(f'{v:.3f}' for v in r['held_out_r2'])} "
                f"| {min(r['held_out_r2']):.3f} | {r['train_steps_per_s']:.1f} | {r['relabel_frames_per_s']:.0f} |"
                for r in data["resolution"]
            ],
            "",
        ]
    if data.get("downstream"):
        lines += [
            "## LeRobot's ACT on true actions vs IDM labels",
            "",
            _commands(data, "downstream"),
            "",
            "Per env: an expert dataset with its true actions (a), and the same dataset stripped of `action` "
            "(LeRobot's `remove_feature`) and relabelled by an IDM trained with `--policy.supervised=true` on 20% "
            "of its episodes (LeRobot's `delete_episodes`, no package metadata) (b). ACT is trained on each with "
            "`lerobot-train` under the same flags and seeds and evaluated by LeRobot's `eval_policy_all` on the same "
            "seeds. Target: (b) ≥ 0.9 × (a).",
            "",
            "ACT settings: `chunk10` plays each 10-action chunk open loop, `replan` predicts a chunk every step and "
            "plays its first action, `ensemble` averages every chunk's prediction for the step (ACT's temporal "
            "ensembling, coefficient 0.01), `fit` is `chunk10` without the VAE and dropout at learning rate 1e-3 (a "
            "scripted expert has one action per state), `fit_step` is `fit` with one-action chunks (`chunk_size=1`: "
            "ACT as a per-step policy). Standard deviations over seeds with ddof = 1. The last "
            "column is how well ACT fits its own training data: R² per action dimension of the first action of a "
            "chunk predicted on every third training frame (mean over seeds; – where not measured).",
            "",
            "Diffusion (`--policy diffusion`) is LeRobot's Diffusion Policy with its defaults (2 observations, a "
            "64-action horizon of which it plays 32 open loop, DDPM with 100 steps, learning rate 1e-4 with warm-up "
            "and cosine decay) and a U-Net of widths 64, 128, 256 instead of 512, 1024, 2048, sized for a CPU; its "
            "training-fit column reads every 30th training frame. "
            "*Commit*: the code that labelled and trained the row (– for rows from before it was recorded). "
            "*Training s* and *evaluation s*: one run's wall seconds, mean over seeds, with `--jobs` runs sharing the "
            "machine's cores (– where a row does not record them); a run resumed from a shorter one of the same arm "
            "(a larger `--steps`) counts the steps after that one's.",
            "",
            "| env | policy | steps | commit | labels | seeds | success rate per seed | mean ± std | return (mean) "
            "| training-frame R² | training s | evaluation s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        rows = data["downstream"]
        summary = {}
        setting_of = lambda r: (_policy(r), r["act_steps"], r.get("commit") or "–")  # noqa: E731
        for env in dict.fromkeys(r["env"] for r in rows):
            for setting in dict.fromkeys(setting_of(r) for r in rows if r["env"] == env):
                same = [r for r in rows if r["env"] == env and setting_of(r) == setting]
                for arm in dict.fromkeys(_labels(r) for r in same):
                    mine = sorted((r for r in same if _labels(r) == arm), key=lambda r: r["seed"])
                    rates = np.array([r["success_rate"] for r in mine])
                    summary[(env, *setting, arm)] = rates.mean()
                    spread = rates.std(ddof=1) if len(rates) > 1 else float("nan")
                    lines.append(
                        f"| {env} | {' | '.join(map(str, setting))} | {arm} | {len(mine)} "
                        f"| {', '.join(f'{x:.2f}' for x in rates)} | {rates.mean():.3f} ± {_f(spread)} "
                        f"| {np.mean([r['avg_sum_reward'] for r in mine]):.2f} | {_fit(mine)} "
                        f"| {_seconds(mine, 'train_s')} | {_seconds(mine, 'eval_s')} |"
                    )
        lines += [
            "", "| env | policy | steps | commit | labels | (b) / (a) | target 0.9 |", "|---|---|---|---|---|---|---|"
        ]  # fmt: skip
        for (env, *setting, arm), b in summary.items():
            if arm == "true" or (env, *setting, "true") not in summary:
                continue
            a = summary[(env, *setting, "true")]
            ratio = b / a if a > 0 else float("nan")
            met = "met" if ratio >= 0.9 else "missed"
            if a < MEASURABLE:
                met = f"no pair: (a) is below {MEASURABLE} (the policy did not learn the task from the true actions)"
            lines.append(f"| {env} | {' | '.join(map(str, setting))} | {arm} | {_f(ratio)} | {met} |")
        lines.append("")
    if data.get("downstream_findings"):
        lines += ["### Reading", "", *[f"- {f}" for f in data["downstream_findings"]], ""]
    if data.get("downstream_labels"):
        lines += [
            "### The labels of (b), against the stripped true actions (frames with a successor, on the episodes "
            "the IDM did not train on)",
            "",
            "| env | commit | k | IDM reads | IDM trained on (episodes) | scored frames | R² | R² per dimension "
            "| R² of the effect | engines on/off agree |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for q in data["downstream_labels"]:
            per_dim = ", ".join(_f(x) for x in q["r2_per_dim"])
            lines.append(
                f"| {q['env']} | {q.get('commit') or '–'} | {q.get('idm_context', 0)}"
                f"{f', pulled {pull:g}σ' if (pull := q.get('pull_to_observation')) else ''} "
                f"| {q.get('idm_reads') or '–'} "
                f"| {q['labelled_episodes']} of {q['episodes']} | {q['frames']}"
                f"{'' if q.get('scored_episodes') else ' (all episodes: before held-out scoring)'} | {_f(q['r2'])} | "
                f"{per_dim} | {_f(q.get('effect_r2'))} | "
                f"{', '.join(_f(x) for x in q['engine_agreement']) if 'engine_agreement' in q else '–'} |"
            )
        lines.append("")
    if data.get("context"):
        lines += [
            "## IDM accuracy against the context k (frames t−k … t+1+k)",
            "",
            _commands(data, "context"),
            "",
            "| env | k | IDM training data | held-out frames | agreement (discrete) / R² (continuous) "
            "| R² of the effect |",
            "|---|---|---|---|---|---|",
        ]
        for r in data["context"]:
            lines.append(
                f"| {r['env']} | {r['k']} | {r['trained_on']} | {r['frames']} | {_f(r['score'], 4)} | "
                f"{_f(r.get('effect_r2'), 4)} |"
            )
        lines.append("")
    if data.get("accuracy"):
        lines += [
            "## Label accuracy of IUPE checkpoints (expert data on unseen seeds, actions stripped, relabelled)",
            "",
            _commands(data, "accuracy"),
            "",
            "| env | episodes | frames compared | agreement |",
            "|---|---|---|---|",
            *[
                f"| {a['env']} | {a['episodes']} | {a['frames_compared']} | {a['agreement']:.4f} |"
                for a in data["accuracy"]
            ],
            "",
        ]
    if data.get("throughput"):
        lines += [
            "## Throughput",
            "",
            _commands(data, "throughput"),
            "",
            "| dataset | processes | relabel frames/s | plain decode frames/s | ratio |",
            "|---|---|---|---|---|",
        ]
        for r in data["throughput"]:
            decode = f"{r['decode_fps']:.0f}" if r.get("decode_fps") else "–"
            ratio = f"{r['relabel_fps'] / r['decode_fps']:.2f}" if r.get("decode_fps") else "–"
            lines.append(f"| {r['dataset']} | {r.get('processes', 1)} | {r['relabel_fps']:.0f} | {decode} | {ratio} |")
        lines.append("")
        if data.get("throughput_findings"):
            lines += ["### Reading", "", *[f"- {f}" for f in data["throughput_findings"]], ""]
    return "\n".join(lines)
