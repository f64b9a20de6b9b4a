"""Speed at real size, before and after, in one run on one machine: the code of a baseline revision (a git worktree
put first on PYTHONPATH) and this tree, on the same data.

- Training steps/s of ``lerobot-train`` with default flags (batch 8, LeRobot's 4 loader workers) on the two-camera
  640×480 arm recording (``lerobot_iupe.data.arm_recording``): the camera IDM (``--policy.joint_state_columns=[]``)
  and the default one for an arm (joint states). Steps/s is 1 / (update + data time) as lerobot-train logs them,
  over the later half of the run (the frame cache is built in the first logging interval).
- The 64×64 path: supervised training on a maze expert recording (video cameras), same data and steps.
- Relabelling frames/s with the camera IDM, 1 and all worker processes, with and without the pull toward the
  observation (a fixed-cost fit after labelling), against a plain decode of the same videos with as many processes
  (each decoding a contiguous share of every video whole, full size to RGB, one thread) by torchcodec and by PyAV,
  and peak memory (``/usr/bin/time``).
- Decoder costs (``--only decoders``): ms per frame of one 640×480 camera video on one thread, in a fresh process per
  rule, rounds alternated: full-size RGB by torchcodec and PyAV, torchcodec's ``Resize`` to the working size, the
  same steps through PyAV (RGB at full size, then scaled), and PyAV's one scaler pass (``data.video.CameraFrames``).

    python benchmarks/measure/speed.py [--frames 2000] [--baseline d03e093] [--steps 300] [--work outputs/speed]

Relabelling's "before" runs the baseline's code on this tree's checkpoint: it needs a baseline that reads it and has
``--num_workers`` (``--only relabel --baseline 5a43bd2``; d03e093 has neither).

Writes benchmarks/speed.json and benchmarks/speed.md.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from steps import command_line, resolution_of  # noqa: E402

BIN = Path(sys.executable).parent
REPO = Path(__file__).resolve().parents[2]
CHECKPOINT = "checkpoints/last/pretrained_model"
EPISODE_FRAMES = 250


def run(command: list[str], env: dict) -> tuple[str, float, float]:
    """Run ``command``: its output, wall seconds and peak resident GB (largest process, ``/usr/bin/time``)."""
    print("$", " ".join(command), flush=True)
    start = time.perf_counter()
    result = subprocess.run(
        ["/usr/bin/time", "-f", "MAXRSS_KB %M", *command], capture_output=True, text=True, env={**os.environ, **env}
    )
    seconds = time.perf_counter() - start
    output = result.stdout + result.stderr
    if result.returncode:
        print(output[-4000:])
        raise SystemExit(f"{command[0]} failed ({result.returncode})")
    return output, seconds, int(re.findall(r"MAXRSS_KB (\d+)", output)[-1]) / 1024**2


def code_env(code: Path | None, cache: Path) -> dict:
    """The environment that runs the code of ``code`` (a worktree; None: this tree) with a shared frame cache."""
    env = {"LEROBOT_IUPE_CACHE": str(cache), "PYTHONPATH": str(code or REPO)}
    return env


def worktree(work: Path, revision: str) -> Path:
    path = work / f"code-{revision}"
    if not path.exists():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", str(path), revision], check=True)
    return path


def steps_per_s(output: str) -> float:
    updates = [(float(u), float(d)) for u, d in re.findall(r"updt_s:([\d.]+) data_s:([\d.]+)", output)]
    later = updates[len(updates) // 2 :]
    return 1.0 / float(np.mean([u + d for u, d in later]))


def train(root: Path, out: Path, steps: int, env: dict, *extra: str) -> dict:
    output, seconds, peak = run(
        [str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
         f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", f"--output_dir={out}",
         f"--steps={steps}", f"--save_freq={steps}", f"--log_freq={max(1, steps // 6)}", "--policy.device=cpu",
         "--wandb.enable=false", *extra],
        env,
    )  # fmt: skip
    return {"steps_per_s": steps_per_s(output), "seconds": seconds, "peak_rss_gb": peak,
            "resolution": resolution_of(out / CHECKPOINT)}  # fmt: skip


def plain_decode(root: Path, backend: str, share: int, shares: int) -> int:
    """Decode share ``share`` of ``shares`` (contiguous frames) of every video of ``root`` whole at full size on one
    thread; the frames decoded."""
    import torch

    from lerobot_iupe.data.video import open_video

    torch.set_num_threads(1)
    frames = 0
    for path in sorted((root / "videos").rglob("*.mp4")):
        if backend == "torchcodec":
            from torchcodec.decoders import VideoDecoder

            decoder = VideoDecoder(str(path), num_ffmpeg_threads=1)
            total = decoder.metadata.num_frames
            lo, hi = total * share // shares, total * (share + 1) // shares
            for first in range(lo, hi, 256):
                frames += len(decoder.get_frames_in_range(first, min(first + 256, hi)).data)
        else:
            container = open_video(path)
            stream = container.streams.video[0]
            total = stream.frames
            lo, hi = total * share // shares, total * (share + 1) // shares
            container.seek(int(lo / stream.average_rate / stream.time_base), stream=stream, backward=True)
            for frame in container.decode(stream):
                index = round(frame.time * float(stream.average_rate))
                if index >= hi:
                    break
                if index >= lo:
                    frame.to_ndarray(format="rgb24")
                    frames += 1
    return frames


def plain_decode_rate(root: Path, backend: str, processes: int) -> float:
    """Dataset frames/s of ``processes`` fresh processes decoding every camera's videos whole between them, timed
    from their first decoded file to their last (the imports of a fresh process are not decoding)."""
    cameras = len({p.relative_to(root / "videos").parts[0] for p in (root / "videos").rglob("*.mp4")})
    commands = [[sys.executable, __file__, "--decode", str(root), "--backend", backend, "--share", str(i),
                 "--shares", str(processes)] for i in range(processes)]  # fmt: skip
    children = [subprocess.Popen(c, stdout=subprocess.PIPE, text=True) for c in commands]
    counted = [child.communicate()[0].split()[-2:] for child in children]  # (frames, decoding seconds) each
    return sum(int(f) for f, _ in counted) / cameras / max(float(t) for _, t in counted)


DECODER_RULES = {
    "torchcodec, full-size RGB": "tc-full",
    "torchcodec's Resize (RGB at full size, then scaled)": "tc-resize",
    "PyAV, full-size RGB": "av-full",
    "PyAV, RGB at full size, then scaled (torchcodec's steps)": "av-two-pass",
    "PyAV, one scaler pass to RGB at the working size (the package's rule)": "av-one-pass",
}


def decode_with_rule(path: Path, rule: str, shape: tuple[int, int], count: int) -> float:
    """Ms per frame of the first ``count`` frames of ``path`` decoded by ``rule`` on one thread."""
    import torch

    from lerobot_iupe.data.video import open_video

    torch.set_num_threads(1)
    start = time.perf_counter()
    if rule.startswith("tc"):
        from torchcodec.decoders import VideoDecoder
        from torchcodec.transforms import Resize

        decoder = VideoDecoder(
            str(path), num_ffmpeg_threads=1, transforms=[Resize(shape)] if rule == "tc-resize" else None
        )
        for first in range(0, count, 250):
            decoder.get_frames_in_range(first, min(first + 250, count))
    else:
        container = open_video(path)
        for n, frame in enumerate(container.decode(container.streams.video[0]), 1):
            if rule == "av-full":
                frame.to_ndarray(format="rgb24")
            elif rule == "av-two-pass":
                rgb = frame.reformat(format="rgb24")
                rgb.reformat(width=shape[1], height=shape[0], interpolation="BILINEAR").to_ndarray()
            else:
                frame.reformat(width=shape[1], height=shape[0], format="rgb24", interpolation="BILINEAR").to_ndarray()
            if n == count:
                break
    return (time.perf_counter() - start) / count * 1e3


def decoder_costs(root: Path, rounds: int = 3, count: int = 1000) -> dict:
    """Median ms per frame of each rule over ``rounds`` alternated fresh processes, on the front camera's video."""
    path = sorted((root / "videos").rglob("*.mp4"))[0]
    times: dict[str, list[float]] = {name: [] for name in DECODER_RULES}
    for _ in range(rounds):
        for name, rule in DECODER_RULES.items():
            command = [sys.executable, __file__, "--decode", str(path), "--rule", rule, "--count", str(count)]
            times[name].append(float(subprocess.run(command, capture_output=True, text=True, check=True).stdout))
    return {name: float(np.median(values)) for name, values in times.items()}


def relabel(checkpoint: Path, root: Path, env: dict, *extra: str) -> dict:
    output, seconds, peak = run(
        [str(BIN / "lerobot-iupe-relabel"), f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{root.name}",
         f"--dataset.root={root}", "--dry_run=true", *extra],
        env,
    )  # fmt: skip
    return {"frames_per_s": float(re.search(r"\((\d+) frames/s\)", output).group(1)), "peak_rss_gb": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2000, help="frames of the camera recording")
    parser.add_argument("--baseline", default="d03e093", help="the revision measured as 'before'")
    parser.add_argument("--steps", type=int, default=300, help="training steps of each run")
    parser.add_argument("--backend", default="torchcodec", help="the decoder of relabelling and the plain decode")
    parser.add_argument("--work", type=Path, default=Path("outputs/speed"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    parser.add_argument("--only", nargs="+", default=["train", "maze", "relabel"], help="which measurements to run")
    parser.add_argument("--processes", type=int, nargs="+", help="relabelling workers (default: 1 and every core)")
    parser.add_argument("--checkpoint", type=Path, help="the IDM to relabel with (default: --only train's camera IDM)")
    parser.add_argument("--decode", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--share", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--rule", help=argparse.SUPPRESS)
    parser.add_argument("--count", type=int, default=1000, help=argparse.SUPPRESS)
    parser.add_argument("--shares", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.decode and args.rule:
        print(decode_with_rule(args.decode, args.rule, (96, 128), args.count))
        return
    if args.decode:
        import av  # noqa: F401  (imported before the clock starts)
        import torch  # noqa: F401
        import torchcodec.decoders  # noqa: F401

        import lerobot_iupe.data.video  # noqa: F401

        start = time.perf_counter()
        frames = plain_decode(args.decode, args.backend, args.share, args.shares)
        print(frames, time.perf_counter() - start)
        return
    command = command_line()
    work = args.work.resolve()
    cache = work / "frame-cache"
    before, after = code_env(worktree(work, args.baseline), cache), code_env(None, cache)
    root = work / f"arm-{args.frames}"
    if not (root / "meta" / "info.json").exists():
        maker = str(REPO / "scripts/make_arm_recording.py")
        episodes = str(args.frames // EPISODE_FRAMES)
        subprocess.run([sys.executable, maker, "--root", str(root), "--repo_id", f"local/{root.name}", "--episodes",
                        episodes], check=True)  # fmt: skip
    path = args.out / "speed.json"
    results = json.loads(path.read_text()) if path.exists() else {"commands": {}}
    cores = len(os.sched_getaffinity(0))
    machine = f"{cores} cores"

    if "train" in args.only:
        rows = []
        camera = ["--policy.joint_state_columns=[]"]
        # (row, tag, the flags of both, this tree's own): the IDM alone is what a relabelling run needs; the baseline
        # has no --policy.idm_only and trains its policy model too, as any run of its did
        variants = (
            ("camera IDM", "camera", camera, []),
            ("arm IDM (default)", "arm", [], []),
            ("camera IDM trained alone (--policy.idm_only=true; before: with its policy model)", "camera-alone",
             camera, ["--policy.idm_only=true"]),
        )  # fmt: skip
        for idm, tag, extra, own in variants:
            row = {
                "idm": idm,
                "frames": args.frames,
                "steps": args.steps,
                "machine": machine,
                "baseline": args.baseline,
            }
            for name, env in (("before", before), ("after", after)):
                out = work / f"train-{name}-{tag}-{args.frames}"
                subprocess.run(["rm", "-rf", str(out)], check=True)
                row[name] = train(root, out, args.steps, env, *extra, *(own if name == "after" else []))
            row["speedup"] = row["after"]["steps_per_s"] / row["before"]["steps_per_s"]
            print(row, flush=True)
            rows.append(row)
        for row in rows:
            row["resolution"] = row["after"]["resolution"]
        keep(results, "train", rows, command, ("frames", "idm", "baseline", "resolution"))

    if "maze" in args.only:
        maze = work / "maze5-expert"
        if not (maze / "meta" / "info.json").exists():
            run([str(BIN / "lerobot-iupe-collect"), "--env.type=maze", "--env.size=5", "--agent=expert",
                 "--episodes=40", "--keep_actions=true", "--dataset.repo_id=local/maze5-expert",
                 f"--dataset.root={maze}"], after)  # fmt: skip
        row = {"data": "maze 5×5, 40 expert episodes, 64×64 video", "steps": args.steps, "machine": machine}
        for name, env in (("before", before), ("after", after)):
            out = work / f"train-{name}-maze"
            subprocess.run(["rm", "-rf", str(out)], check=True)
            row[name] = train(maze, out, args.steps, env, "--batch_size=64")
            row[f"{name}_relabel"] = relabel(out / CHECKPOINT, maze, env)
        row["speedup"] = row["after"]["steps_per_s"] / row["before"]["steps_per_s"]
        row["relabel_speedup"] = row["after_relabel"]["frames_per_s"] / row["before_relabel"]["frames_per_s"]
        print(row, flush=True)
        keep(results, "maze", [row], command, ("data",))

    if "decoders" in args.only:
        costs = decoder_costs(root)
        rows = [
            {"frames": args.frames, "machine": machine, "rule": name, "ms_per_frame": ms} for name, ms in costs.items()
        ]
        print(rows, flush=True)
        keep(results, "decoders", rows, command, ("frames", "rule"))

    if "relabel" in args.only:
        checkpoint = args.checkpoint or work / f"train-after-camera-{args.frames}" / CHECKPOINT
        rows = []
        backend = f"--dataset.video_backend={args.backend}"
        for workers in args.processes or sorted({1, cores}):
            plain = plain_decode_rate(root, args.backend, workers)
            plain_pyav = plain_decode_rate(root, "pyav", workers)
            before_rate = relabel(checkpoint, root, before, backend, f"--num_workers={workers}")
            measured = relabel(checkpoint, root, after, backend, f"--num_workers={workers}")
            unpulled = relabel(checkpoint, root, after, backend, f"--num_workers={workers}", "--pull_to_observation=0")
            rows.append({
                "frames": args.frames, "backend": args.backend, "processes": workers, "machine": machine,
                "relabel_frames_per_s": measured["frames_per_s"], "peak_rss_gb": measured["peak_rss_gb"],
                "unpulled_frames_per_s": unpulled["frames_per_s"], "plain_decode_pyav_frames_per_s": plain_pyav,
                "plain_decode_frames_per_s": plain, "ratio": measured["frames_per_s"] / plain,
                "before_frames_per_s": before_rate["frames_per_s"], "before_peak_rss_gb": before_rate["peak_rss_gb"],
                "baseline": args.baseline, "before_processes": workers, "resolution": resolution_of(checkpoint),
            })  # fmt: skip
            print(rows[-1], flush=True)
        keep(results, "relabel", rows, command, ("frames", "processes", "baseline", "resolution"))

    args.out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=1) + "\n")
    render(results, args.out / "speed.md")


def keep(results: dict, section: str, rows: list[dict], command: str, key: tuple[str, ...]) -> None:
    """Put ``rows`` into ``section`` in place of those with the same ``key``; the section's commands so far."""
    new = {tuple(r.get(k) for k in key) for r in rows}
    results[section] = [r for r in results.get(section, []) if tuple(r.get(k) for k in key) not in new] + rows
    commands = results["commands"].get(section, [])
    commands = [commands] if isinstance(commands, str) else commands
    results["commands"][section] = commands + [command] if command not in commands else commands


def commands_of(results: dict, section: str) -> str:
    commands = results["commands"][section]
    return ", ".join(f"`{c}`" for c in ([commands] if isinstance(commands, str) else commands))


def fmt(value: float | None, digits: int = 0) -> str:
    """A figure to ``digits`` decimals; a dash where the row has none."""
    return "—" if value is None else f"{value:.{digits}f}"


def render(results: dict, page: Path) -> None:
    lines = ["# Speed at real size", "", "Every ratio is measured in one run of the script on one machine, the "
             "baseline revision's code beside this tree's, on the same data. Written by `benchmarks/measure/speed.py`.",
             ""]  # fmt: skip
    if "train" in results:
        lines += ["## Training (lerobot-train, default flags, batch 8)", "", commands_of(results, "train"), "",
                  "| IDM | frames | steps | machine | working resolution: before → after | before: revision | "
                  "before steps/s | after steps/s | speedup | before peak GB | after peak GB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in results["train"]:
            b, a = r["before"], r["after"]
            resolutions = f"{b.get('resolution', '96×128')} → {a.get('resolution', '96×128')}"
            lines.append(f"| {r['idm']} | {r['frames']:,} | {r['steps']} | {r['machine']} | {resolutions} | "
                         f"{r.get('baseline', 'd03e093')} | {b['steps_per_s']:.1f} | "
                         f"{a['steps_per_s']:.1f} | {r['speedup']:.2f}× | {b['peak_rss_gb']:.2f} | "
                         f"{a['peak_rss_gb']:.2f} |")  # fmt: skip
        lines += ["", "One run's after/before moves by about ±10% on this machine: the camera IDM's 2,000-frame row "
                  "read 10.5 steps/s at 4dd0cab and 12.9 at 80d3887 with the same training code; 300 steps of each, "
                  "alternating (`benchmarks/measure/speed.py`'s `train`), gave 11.9 and 11.2 at 80d3887 against 11.9 "
                  "and 11.6 at fda618c. The camera IDM trained alone (`--policy.idm_only=true`) trains no policy "
                  "model: the baseline, which has no such flag, trains its own. The 59efeed rows time the allocator "
                  "setting that keeps freed memory (`policy/threads.py`), made for relabelling's IDM passes (batch "
                  "32); one run each (0.95×, 1.30×) shows no effect on training beyond this machine's noise, which "
                  "was larger that day: the d03e093 2,000-frame rows, run an hour earlier, read 2.22× where an "
                  "earlier run read 2.81×. The 96×128 → 72×96 rows run each revision at its default working "
                  "resolution (72×96 here since cdf13eb). The camera IDM again, alternated the same hour (300 steps, "
                  "4 and 3 runs): 14.0–18.7 steps/s at 72×96 and 13.3–14.9 at 96×128 against d03e093's 4.9–5.1, so "
                  "2.7–3.7× (mean 3.4×) at the default and 2.6–3.0× at 96×128 (benchmarks/findings.md, seventh "
                  "pass).", ""]  # fmt: skip
    if "maze" in results:
        lines += ["## The 64×64 path", "", commands_of(results, "maze"), "",
                  "| data | steps | before steps/s | after steps/s | speedup | before relabel frames/s | "
                  "after relabel frames/s | ratio |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in results["maze"]:
            lines.append(f"| {r['data']} (batch 64) | {r['steps']} | {r['before']['steps_per_s']:.1f} | "
                         f"{r['after']['steps_per_s']:.1f} | {r['speedup']:.2f}× | "
                         f"{r['before_relabel']['frames_per_s']:.0f} | {r['after_relabel']['frames_per_s']:.0f} | "
                         f"{r['relabel_speedup']:.2f}× |")  # fmt: skip
        lines.append("")
    if "relabel" in results:
        lines += ["## Relabelling with the camera IDM", "", commands_of(results, "relabel"), "",
                  "Frames/s are the report's: decoding, labelling and the pull toward the observation, a fit of about"
                  " 6–9 s on one core whatever the dataset's size (on by default for this IDM); 'without the pull' is"
                  " the same run with `--pull_to_observation=0`. The plain decodes convert every frame to RGB at full"
                  " size, one thread a process, torchcodec's (the limit the issue names) and PyAV's (the faster on "
                  "these AV1 files). Rows without the later columns were measured before they existed. The c96015a "
                  "and 59efeed rows relabel with a camera IDM trained on the same recording by `lerobot-train "
                  "--policy.type=iupe --policy.supervised=true --policy.joint_state_columns=[] --policy.idm_only=true"
                  " --steps=300` (`--checkpoint`); before c96015a, PyAV's decoder started a thread per core in every "
                  "process (libdav1d ignores `thread_type`). The machine ran the 59efeed rows' plain decodes 20% "
                  "slower than the c96015a rows' (174 against 217 frames/s): compare ratios within a row. The 72×96 "
                  "rows (the default working resolution since cdf13eb) relabel with the camera IDM trained alone by "
                  "`--only train` on the 2,000-frame recording at the default, 300 steps; benchmarks/findings.md "
                  "(seventh pass) compares the resolutions in alternated runs.", "",
                  "| frames | decoder | processes | machine | working resolution | relabel frames/s | without the pull"
                  " | plain decode, "
                  "torchcodec | plain decode, PyAV | ratio to torchcodec's | without the pull | ratio to PyAV's, "
                  "without the pull | peak GB | before: revision, processes | before frames/s | before peak GB |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in results["relabel"]:
            unpulled, plain = r.get("unpulled_frames_per_s"), r["plain_decode_frames_per_s"]
            pyav = r.get("plain_decode_pyav_frames_per_s")
            cells = [f"{r['frames']:,}", r["backend"], r["processes"], r["machine"], r.get("resolution", "96×128"),
                     fmt(r["relabel_frames_per_s"]),
                     fmt(unpulled), fmt(plain), fmt(pyav), fmt(r["ratio"], 2), fmt(unpulled and unpulled / plain, 2),
                     fmt(unpulled and pyav and unpulled / pyav, 2), fmt(r["peak_rss_gb"], 2),
                     f"{r.get('baseline', 'd03e093')}, {r.get('before_processes', 1)}",
                     fmt(r["before_frames_per_s"]), fmt(r["before_peak_rss_gb"], 2)]  # fmt: skip
            lines.append("| " + " | ".join(str(c) for c in cells) + " |")
        lines.append("")
    if "decoders" in results:
        lines += ["## What a frame costs to decode", "", commands_of(results, "decoders"), "",
                  "One 640×480 AV1 camera (the recording's front camera), the first 1,000 frames, one thread (PyAV's "
                  "`thread_count=1`: libdav1d ignores `thread_type`, and uncounted it starts a thread per core), a "
                  "fresh process per rule, the median of 3 alternated rounds; 96×128 is the working size.", "",
                  "| frames | machine | rule | ms per frame |", "|---|---|---|---|"]  # fmt: skip
        for r in results["decoders"]:
            lines.append(f"| {r['frames']:,} | {r['machine']} | {r['rule']} | {r['ms_per_frame']:.2f} |")
        lines.append("")
    page.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
