"""``lerobot-iupe-relabel``'s flags (LeRobot's names: ``--policy.*``, ``--dataset.*``) and its report."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lerobot_iupe.data.storage import WrittenDataset

MODES = ("argmax", "sample")


@dataclass
class CheckpointRef:
    # A trained IUPE checkpoint: .../checkpoints/<step>/pretrained_model, or a hub model id (as for lerobot-eval).
    path: str | None = None
    # Where the IDM runs: cpu (the default: the same labels on every machine), cuda, mps.
    device: str = "cpu"


@dataclass
class RelabelDataset(WrittenDataset):
    # Video decoder of full-size frames and LeRobot's reader: "pyav" or "torchcodec"; default: torchcodec where it
    # loads, else pyav (LeRobot's rule). Frames the IDM reads at a smaller working resolution are decoded by PyAV
    # and scaled by FFmpeg's scaler either way, as training's frame cache reads them (0.77x torchcodec's time).
    video_backend: str | None = None


# Flags that were top-level before they took LeRobot's names.
RENAMED_FLAGS = {
    "--device": "--policy.device",
    "--video_backend": "--dataset.video_backend",
    "--push_to_hub": "--dataset.push_to_hub",
}


@dataclass
class RelabelConfig:
    policy: CheckpointRef = field(default_factory=CheckpointRef)
    dataset: RelabelDataset = field(default_factory=RelabelDataset)
    # argmax: the IDM's most likely action (a Gaussian's mean); sample: one draw per frame (seeded by --seed and
    # the episode, so it does not depend on the number of processes).
    mode: str = "argmax"
    # Seed of the draws of --mode=sample (unused by argmax).
    seed: int = 0
    # Frames per IDM batch; frames are read (video decoded) in spans of this size, so memory follows the batch,
    # not the dataset.
    batch_size: int = 512
    # CPU threads of the IDM per process. Torch's sums differ in the last bit between thread counts, so a fixed
    # count keeps the labels the same whatever the number of processes; scale out with torchrun (one process per
    # core) rather than threads.
    num_threads: int = 1
    # Processes that decode the frames and, with --policy.device=cpu, run the IDM on them, each taking whole
    # episodes: labels are the same whatever the number. Default: one per core this process may use (shared among
    # torchrun's processes); 0: all in this process.
    num_workers: int | None = None
    # Continuous actions: move each label toward a regression of the labels on the frame's vector observations
    # (observation.state, observation.environment_state), fitted on the whole dataset, by at most this many of the
    # IDM's standard deviations; 0 keeps the IDM's own labels. It takes out errors that drift with the state, which
    # chunked policies (ACT, Diffusion) learn as if they were the expert's (benchmarks/relabel.md). Default: 1 for
    # an IDM of cameras and state on a dataset with a vector observation; 0 for the arm IDM (its labels follow the
    # joints, and the pull lowered their R²), for discrete actions and for datasets without a vector observation.
    pull_to_observation: float | None = None
    # Replace an `action` feature the dataset already has.
    overwrite: bool = False
    # Label and report statistics, write nothing.
    dry_run: bool = False

    def validate(self) -> None:
        if not self.policy.path:
            raise ValueError("--policy.path is required: a trained IUPE checkpoint (.../pretrained_model)")
        if self.mode not in MODES:
            raise ValueError(f"--mode={self.mode} is not known; use one of {list(MODES)}")
        if self.num_threads < 1:
            raise ValueError(f"--num_threads must be at least 1, got {self.num_threads}")
        if self.num_workers is not None and self.num_workers < 0:
            raise ValueError(f"--num_workers must be 0 (no worker processes) or more, got {self.num_workers}")
        if self.pull_to_observation is not None and self.pull_to_observation < 0:
            raise ValueError(
                f"--pull_to_observation must be 0 (the IDM's own labels) or more, got {self.pull_to_observation}"
            )
        if self.batch_size < 1:
            raise ValueError(f"--batch_size must be at least 1, got {self.batch_size}")
        if self.dataset.video_backend not in (None, "pyav", "torchcodec"):
            raise ValueError(
                f"--dataset.video_backend={self.dataset.video_backend} is not known; use pyav or torchcodec"
            )
        if self.dry_run and self.dataset.push_to_hub:
            raise ValueError("--dry_run=true writes nothing, so --dataset.push_to_hub=true has nothing to push")


@dataclass
class RelabelReport:
    root: Path
    checkpoint: str
    mode: str
    frames: int
    episodes: int
    action_names: list[str]
    # Discrete: frames per action id. Continuous: the labels' mean per dimension.
    action_summary: list[float]
    # Discrete: the IDM's mean probability of its label. Continuous: its mean predicted standard deviation, in
    # units of the action range (0 = certain).
    mean_confidence: float
    # Against the action the dataset already had (frames with a successor): the share of equal labels (discrete)
    # or R² (continuous).
    agreement_with_existing: float | None
    seconds: float
    # Continuous: R² of each action dimension against the existing actions (None without them).
    agreement_per_dimension: list[float] | None = None
    # The arm model's references on the same frames, per dimension (``relabel.references``): "ridge" (R² of the
    # plain ridge regression on the IDM's own training data and window), "copy" and "copy_lag" (the best a_t ≈ s_{t+k}),
    # "thumbnails" (a camera dimension's ridge on grey thumbnails; NaN elsewhere).
    references: dict | None = None
    processes: int = 1
    written: bool = False
    # Under torchrun only process 0 gathers, writes and reports; the others return a report with this False.
    first_process: bool = True
    continuous: bool = False
    # --pull_to_observation as applied (its default resolved): the labels' largest move, in the IDM's stds.
    pull_to_observation: float = 0.0

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(self.seconds, 1e-9)

    def summary(self) -> str:
        if self.continuous:
            means = zip(self.action_names, self.action_summary, strict=True)
            labels = "mean label " + ", ".join(f"{n}={v:.3f}" for n, v in means)
            labels += f"; mean IDM std {self.mean_confidence:.3f} of the action range"
            if self.pull_to_observation:
                labels += f"; pulled toward the observation by up to {self.pull_to_observation:g} std"
            agreement = "R² against"
        else:
            total = max(sum(self.action_summary), 1)
            labels = "actions " + ", ".join(f"{a}: {c / total:.1%}" for a, c in enumerate(self.action_summary))
            labels += f"; mean IDM confidence {self.mean_confidence:.3f}"
            agreement = "agreement with"
        processes = f" on {self.processes} processes" if self.processes > 1 else ""
        lines = [
            f"{'wrote' if self.written else 'dry run, nothing written:'} {self.frames} frames of {self.episodes} "
            f"episodes labelled ({self.mode}) in {self.seconds:.1f}s{processes} "
            f"({self.frames_per_second:.0f} frames/s)",
            f"  {labels}",
        ]
        if self.agreement_with_existing is not None:
            lines.append(f"  {agreement} the dataset's existing actions: {self.agreement_with_existing:.4f}")
        if self.agreement_per_dimension and self.references:
            lines += self.reference_table()
        elif self.agreement_per_dimension:
            per = zip(self.action_names, self.agreement_per_dimension, strict=True)
            lines.append("  R² per dimension: " + ", ".join(f"{n}={v:.4f}" for n, v in per))
        return "\n".join(lines)

    def reference_table(self) -> list[str]:
        """R² per dimension of the IDM (with its lag in frames) beside its references — the ridge regression, the best
        copy s_{t+k} of the state of the same name and the best difference copy g·(s_{t+d+1} − s_{t+d}) + b of the
        column of the same name or stem — and the source the IDM reads ("–": no such column); a camera dimension's
        ridge is on 32×24 grey thumbnails of its frames. A dimension where the IDM is more than 0.005 below the ridge
        regression or a copy is marked."""
        refs = self.references
        width = max(len(n) for n in self.action_names)
        lines = [
            f"  {'R² per dimension':<{width}}  {'IDM':>7}  {'lag':>3}  {'ridge':>7}  {'copy s_{t+k}':>14}  "
            f"{'difference copy':>15}  source"
        ]
        count = len(self.action_names)
        lags = refs.get("lag") or [None] * count
        differences = refs.get("difference") or [float("nan")] * count
        difference_lags = refs.get("difference_lag") or [-99] * count
        kinds = refs.get("source") or ["position"] * count
        thumbnails = refs.get("thumbnails") or [float("nan")] * count
        ridges = [r if np.isnan(t) else t for r, t in zip(refs["ridge"], thumbnails, strict=True)]
        kinds = [k if np.isnan(t) else f"{k} (ridge on thumbnails)" for k, t in zip(kinds, thumbnails, strict=True)]
        rows = zip(
            self.action_names, self.agreement_per_dimension, lags, ridges, refs["copy"], refs["copy_lag"],
            differences, difference_lags, kinds, strict=True,
        )  # fmt: skip
        for name, idm, lag, ridge, copy, copy_lag, difference, difference_lag, kind in rows:
            copies = [value for value in (copy, difference) if not np.isnan(value)]
            mark = "  ← below the ridge regression" if idm < ridge - 0.005 else ""
            if copies and idm < max(copies) - 0.005:
                mark += "  ← below a copy"
            copied = f"{copy:7.4f} (k={copy_lag})" if copy_lag >= 0 else f"{'–':>7}" + " " * 7
            differenced = f"{difference:7.4f} (d={difference_lag:>2})" if difference_lag > -99 else f"{'–':>15}"
            lag_text = "–" if lag is None else str(lag)
            lines.append(
                f"  {name:<{width}}  {idm:7.4f}  {lag_text:>3}  {ridge:7.4f}  {copied}  {differenced}  {kind}{mark}"
            )
        return lines
