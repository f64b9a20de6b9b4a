"""Where the time of a training step and of a relabel goes: cProfile of ``lerobot-train`` (camera IDM, batch 8,
``--num_workers=0`` so that loading runs in the profiled process) and of ``lerobot-iupe-relabel --num_workers=0``
(decoding and labelling in one process), each with the code of a baseline revision and of this tree.

    python benchmarks/measure/profile_speed.py [--frames 2000] [--baseline d03e093] [--steps 60] [--work outputs/speed]

Needs the recording and worktree of ``benchmarks/measure/speed.py`` (made if missing). Writes benchmarks/profiles.md:
per run, the seconds in the calls that dominate (cumulative) and the top functions by own time.
"""

from __future__ import annotations

import argparse
import os
import pstats
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from speed import BIN, CHECKPOINT, REPO, code_env, worktree  # noqa: E402
from steps import command_line  # noqa: E402

# The calls a step or a relabel spends its time in, by the function's name (file:function).
PHASES = {
    "LeRobot's loader: items (get_item)": "dataset_reader.py:get_item",
    "LeRobot's loader: video decoding": "video_utils.py:decode_video_frames",
    "policy forward": "modeling_iupe.py:forward",
    "backward": "_tensor.py:backward",
    "optimizer step": "optimizer.py:wrapper",
    "frame cache build": "frame_cache.py:cached_frames",
    "relabel: decoding (FrameReader.parts)": "readers.py:parts",
    "relabel: IDM outputs": "modeling_iupe.py:labelling_output",
    "relabel: the pull's regression (--pull_to_observation)": "consistency.py:observation_regression",
}


def profile(command: list[str], env: dict, out: Path) -> pstats.Stats:
    """``command`` under cProfile; -P keeps the working directory off sys.path, so PYTHONPATH chooses the code."""
    print("$", " ".join(command), flush=True)
    result = subprocess.run([sys.executable, "-P", "-m", "cProfile", "-o", str(out), *command], capture_output=True,
                            text=True, env={**os.environ, **env})  # fmt: skip
    if result.returncode:
        print(result.stdout[-3000:], result.stderr[-3000:])
        raise SystemExit(f"{command[0]} failed")
    return pstats.Stats(str(out))


def summary(title: str, command: str, stats: pstats.Stats, top: int) -> list[str]:
    rows = stats.stats  # {(file, line, name): (calls, primitive, tottime, cumtime, callers)}
    total = max(v[3] for v in rows.values())
    lines = [f"### {title}", "", f"`{command}` — {total:.1f} s in all", "", "| call | calls | cumulative s | share |",
             "|---|---|---|---|"]  # fmt: skip
    for phase, where in PHASES.items():
        file, name = where.split(":")
        found = [v for (f, _, n), v in rows.items() if f.endswith(file) and n == name]
        if found:
            calls, cumulative = sum(v[0] for v in found), max(v[3] for v in found)
            lines.append(f"| {phase} | {calls} | {cumulative:.2f} | {cumulative / total:.0%} |")
    lines += ["", "| function (own time) | calls | own s |", "|---|---|---|"]
    ranked = sorted(rows.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    for (file, line, name), v in ranked:
        lines.append(f"| `{Path(file).name}:{line}({name})` | {v[0]} | {v[2]:.2f} |")
    return lines + [""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--baseline", default="d03e093")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--top", type=int, default=10)
    parser.add_argument("--work", type=Path, default=Path("outputs/speed"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    args = parser.parse_args()
    work = args.work.resolve()
    cache = work / "frame-cache"
    root = work / f"arm-{args.frames}"
    if not (root / "meta" / "info.json").exists():
        raise SystemExit(f"{root} is missing: run python benchmarks/measure/speed.py --frames {args.frames} first")
    command = command_line()
    lines = ["# Profiles", "", f"`{command}`. cProfile, one process, this machine; cumulative seconds include "
             "the calls below them.", ""]  # fmt: skip
    for name, code in (("before", worktree(work, args.baseline)), ("after", None)):
        env = code_env(code, cache)
        out = work / f"profile-train-{name}"
        subprocess.run(["rm", "-rf", str(out)], check=True)
        train = [str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
                 "--policy.joint_state_columns=[]", f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}",
                 f"--output_dir={out}", f"--steps={args.steps}", f"--save_freq={args.steps}", "--num_workers=0",
                 "--policy.device=cpu", "--wandb.enable=false"]  # fmt: skip
        stats = profile(train, env, work / f"train-{name}.prof")
        lines += summary(f"Training, {name} ({args.steps} steps of batch 8, camera IDM)", " ".join(train[1:]), stats,
                         args.top)  # fmt: skip
        relabel = [str(BIN / "lerobot-iupe-relabel"), f"--policy.path={out / CHECKPOINT}",
                   f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", "--dry_run=true"]  # fmt: skip
        config = (code or REPO) / "lerobot_iupe/relabel/config.py"
        in_process = config.exists() and "num_workers" in config.read_text()
        if in_process:  # revisions before --num_workers decode in a process of their own
            relabel.append("--num_workers=0")
        stats = profile(relabel, env, work / f"relabel-{name}.prof")
        where = "in one process" if in_process else "labelling; its one decoding process is not profiled"
        lines += summary(f"Relabelling, {name} ({args.frames:,} frames, {where})", " ".join(relabel[1:]), stats,
                         args.top)  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "profiles.md").write_text("\n".join(lines).replace(str(work), "outputs/speed").replace(str(REPO), "."))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
