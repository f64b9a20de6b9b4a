"""Real camera data at real sizes: an SO-101-shaped recording written by LeRobot's own writer (two 640×480 AV1
cameras that show the arm, six joint positions, absolute joint targets, 30 fps, episodes of 250 frames;
``lerobot_iupe.data.arm_recording``), at 2,000 and at 20,000 frames.

For each size: a supervised IDM trained with default flags by ``lerobot-train`` (training steps/s, peak resident
memory, and of that what the processes allocated themselves, apart from the pages of the memory-mapped frame cache);
its R² per joint on 10 held-out episodes (``lerobot-iupe-relabel --dry_run=true``); relabelling the training
recording (frames/s against plain decoding of the same videos by one single-threaded process, torchcodec — the
decoder LeRobot picks here — and PyAV; peak memory).

    python benchmarks/measure/cameras.py [--frames 2000 20000] [--steps 2000] [--work outputs/measure-cameras]

Writes the "real_cameras" section of benchmarks/relabel.json and renders benchmarks/relabel.md.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.data.video import open_video

sys.path.insert(0, str(Path(__file__).parent))
from relabel_report import update  # noqa: E402
from steps import BIN, command_line, printed_r2  # noqa: E402

CHECKPOINT = "checkpoints/last/pretrained_model"
EPISODE_FRAMES = 250
HELD_OUT_SEED = 1_000_000


def tree(pid: int) -> list[int]:
    """``pid`` and its descendants."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        found.append(p)
        todo += children.get(p, [])
    return found


def memory_of(pid: int) -> tuple[int, int]:
    """(anonymous, file-backed) resident kB of one process."""
    try:
        status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    except OSError:
        return 0, 0
    kb = lambda key: int(status.get(key, "0 kB").split()[0])  # noqa: E731
    return kb("RssAnon"), kb("RssFile") + kb("RssShmem")


def measured(*command: str, env: dict | None = None) -> dict:
    """Run ``command``; its output, wall time, the largest resident set of any of its processes (the kernel's
    high-water mark, by ``/usr/bin/time``) and, sampled every 0.2 s, the largest anonymous part (what a process
    allocated itself, without the file pages of the memory-mapped frame cache)."""
    print("$", shlex.join(command), flush=True)
    start = time.perf_counter()
    process = subprocess.Popen(
        ["/usr/bin/time", "-f", "MAXRSS_KB %M", *command],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, **(env or {})},
    )  # fmt: skip
    peak_anon = [0]

    def sample() -> None:
        while process.poll() is None:
            for pid in tree(process.pid):
                peak_anon[0] = max(peak_anon[0], memory_of(pid)[0])
            time.sleep(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    output = process.communicate()[0]
    sampler.join()
    seconds = time.perf_counter() - start
    if process.returncode:
        print(output[-4000:])
        raise SystemExit(f"{command[0]} failed ({process.returncode})")
    return {
        "output": output,
        "seconds": seconds,
        "peak_rss_gb": int(re.findall(r"MAXRSS_KB (\d+)", output)[-1]) / 1024**2,
        "peak_anon_gb": peak_anon[0] / 1024**2,
    }


def recording(work: Path, name: str, episodes: int, seed: int) -> Path:
    root = work / name
    if not (root / "meta" / "info.json").exists():
        print(f"writing {root} ({episodes} episodes of {EPISODE_FRAMES} frames)", flush=True)
        write_arm_recording(root, episodes, EPISODE_FRAMES, seed=seed, repo_id=f"local/{name}", progress=True)
    return root


def plain_decode_rate(root: Path, backend: str) -> float:
    """Dataset frames/s of decoding every camera's videos whole at full size, in this process, one thread."""
    import torch

    torch.set_num_threads(1)
    files = sorted((root / "videos").rglob("*.mp4"))
    cameras = len({path.relative_to(root / "videos").parts[0] for path in files})
    start, frames = time.perf_counter(), 0
    for path in files:
        if backend == "torchcodec":
            from torchcodec.decoders import VideoDecoder

            decoder = VideoDecoder(str(path), num_ffmpeg_threads=1)
            total = decoder.metadata.num_frames
            for first in range(0, total, 256):
                frames += len(decoder.get_frames_in_range(first, min(first + 256, total)).data)
        else:
            container = open_video(path)
            for frame in container.decode(container.streams.video[0]):
                frame.to_ndarray(format="rgb24")
                frames += 1
    return frames / cameras / (time.perf_counter() - start)


def decode_rate(root: Path, backend: str) -> float:
    """``plain_decode_rate`` in a fresh process (no decoder state or threads of this one)."""
    command = [sys.executable, __file__, "--decode", str(root), "--backend", backend]
    return float(subprocess.run(command, capture_output=True, text=True, check=True).stdout.split()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[2000, 20000])
    parser.add_argument("--steps", type=int, default=2000, help="training steps of each IDM")
    parser.add_argument("--work", type=Path, default=Path("outputs/measure-cameras"))
    parser.add_argument("--out", type=Path, default=Path("benchmarks"))
    parser.add_argument("--decode", type=Path, help="only print the plain decode rate of this dataset's videos")
    parser.add_argument("--backend", default="torchcodec", help="the decoder of --decode: torchcodec or pyav")
    args = parser.parse_args()
    if args.decode:
        print(f"plain {args.backend} decode, one thread: {plain_decode_rate(args.decode, args.backend):.1f}")
        return
    command = command_line()
    # Its own frame cache, so that each size's first training run builds it (and is measured doing so).
    env = {"LEROBOT_IUPE_CACHE": str(args.work / "frame-cache")}
    held_out = recording(args.work, "arm-held-out", 10, HELD_OUT_SEED)
    rows = []
    for frames in args.frames:
        root = recording(args.work, f"arm-{frames}", frames // EPISODE_FRAMES, 0)
        out = args.work / f"arm-{frames}-idm-{args.steps}"
        train = measured(
            str(BIN / "lerobot-train"), "--policy.type=iupe", "--policy.supervised=true",
            f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", f"--output_dir={out}",
            f"--steps={args.steps}", f"--save_freq={args.steps}", "--log_freq=100", "--policy.device=cpu",
            "--wandb.enable=false", "--policy.joint_state_columns=[]", env=env,  # the camera IDM, not the arm's
        )  # fmt: skip
        updates = [(float(u), float(d)) for u, d in re.findall(r"updt_s:([\d.]+) data_s:([\d.]+)", train["output"])]
        step_s = np.mean([u + d for u, d in updates[len(updates) // 2 :]])  # the later half: the cache is built
        checkpoint = out / CHECKPOINT
        scored = measured(
            str(BIN / "lerobot-iupe-relabel"), f"--policy.path={checkpoint}", "--dataset.repo_id=local/held",
            f"--dataset.root={held_out}", "--dry_run=true", env=env,
        )  # fmt: skip
        r2 = printed_r2(scored["output"])
        row = {
            "frames": frames, "steps": args.steps, "train_steps_per_s": 1.0 / step_s,
            "train_seconds": train["seconds"], "train_peak_rss_gb": train["peak_rss_gb"],
            "train_peak_anon_gb": train["peak_anon_gb"], "held_out_r2": r2,
        }  # fmt: skip
        for backend in ("torchcodec", "pyav"):
            relabel = measured(str(BIN / "lerobot-iupe-relabel"), f"--policy.path={checkpoint}",
                               f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", "--dry_run=true",
                               f"--dataset.video_backend={backend}", env=env)  # fmt: skip
            rate = float(re.search(r"\((\d+) frames/s\)", relabel["output"]).group(1))
            decode = decode_rate(root, backend)
            row[backend] = {
                "relabel_frames_per_s": rate, "decode_frames_per_s": decode, "ratio": rate / decode,
                "relabel_peak_rss_gb": relabel["peak_rss_gb"], "relabel_peak_anon_gb": relabel["peak_anon_gb"],
            }  # fmt: skip
        print(row, flush=True)
        rows.append(row)
    update(args.out, "real_cameras", rows, command, key=("frames", "steps"))


if __name__ == "__main__":
    main()
