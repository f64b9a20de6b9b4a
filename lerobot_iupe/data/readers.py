"""Reading LeRobot datasets fast: whole columns from Arrow, video decoded in spans (one seek per span and camera)
at the policy's working resolution instead of LeRobot's per-item access, which seeks and decodes every frame at
full size; the transitions of a dataset with actions, and the expert dataset at hand for training (cameras from
the frame cache)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.utils.constants import ACTION
from lerobot.utils.feature_utils import dataset_to_policy_features
from torch import Tensor

from lerobot_iupe.data.episodes import EpisodeFrames, column_array, episode_bounds, layout_shapes
from lerobot_iupe.data.frame_cache import cached_frames
from lerobot_iupe.data.observation import ObservationLayout, pack_tensors
from lerobot_iupe.data.transitions import Transitions, context_offsets
from lerobot_iupe.data.video import resize_images


def dataset_layout(meta: LeRobotDatasetMetadata, keys: list[str]) -> ObservationLayout:
    """The layout of these keys as a policy sees them (cameras (C, H, W), by LeRobot's own conversion)."""
    features = dataset_to_policy_features({k: meta.features[k] for k in keys})
    return ObservationLayout(tuple(tuple(features[k].shape) for k in keys))


def stored_frames(dataset: LeRobotDataset, key: str) -> np.ndarray:
    """Every frame of a feature kept in the parquet files: float32 states (N, D), or uint8 (N, C, H, W) images
    (``image`` features: PNGs, decoded by ``datasets``)."""
    if dataset.meta.features[key]["dtype"] == "image":
        images = np.asarray(dataset.hf_dataset.with_format("numpy")[key][:])
        return np.ascontiguousarray(images.transpose(0, 3, 1, 2))
    return column_array(dataset.hf_dataset, key).astype(np.float32)


@dataclass(frozen=True)
class LabelSpan:
    """Frames ``start … stop - 1`` of episode ``episode`` (frames ``first … last``, global indices) to be labelled
    together; the frames ``lo … hi`` they need around them (the IDM's window, clamped into the episode)."""

    episode: int
    first: int
    last: int
    start: int
    stop: int
    lo: int
    hi: int


def label_spans(
    bounds: list[tuple[int, int]], batch_size: int, offsets: list[int], episodes: list[int] | None = None
) -> list[LabelSpan]:
    """Spans of at most ``batch_size`` frames covering every frame with a successor of the chosen episodes
    (default: all); a span never crosses an episode, so its labels do not depend on which others are labelled."""
    spans = []
    for episode in range(len(bounds)) if episodes is None else episodes:
        first, end = bounds[episode]
        last = end - 1
        for start in range(first, last, batch_size):
            stop = min(start + batch_size, last)
            lo, hi = max(first, start + min(offsets)), min(last, stop - 1 + max(offsets))
            spans.append(LabelSpan(episode, first, last, start, stop, lo, hi))
    return spans


# A forked worker's copies of its parent's open decoders (FrameReader.forget_open_files).
INHERITED_DECODERS: list = []


class FrameReader:
    """Frames ``lo … hi`` of one episode for a set of observation keys, read from the files as needed (memory
    follows the span, not the dataset), cameras at ``layout``'s working resolution (resized by the video decoder),
    joined in key order (``ObservationLayout.join``). Vectors and PNG images come from Arrow slices of the parquet
    files, video by one seek per span and camera."""

    def __init__(
        self, dataset: LeRobotDataset, keys: list[str], layout: ObservationLayout, video_backend: str = "pyav"
    ):
        self.dataset, self.meta, self.keys, self.layout = dataset, dataset.meta, keys, layout
        self.episode_frames = EpisodeFrames(dataset, layout_shapes(dataset.meta, keys, layout), video_backend)

    def frames(self, episode: int, first: int, lo: int, hi: int) -> Tensor:
        return self.layout.join(self.parts(episode, lo, hi))

    def forget_open_files(self) -> None:
        """Open new decoders from here on: a forked process must not share its parent's (their state is the
        parent's). The parent's are kept, never freed: freeing an AV1 decoder waits for its decoding threads, which
        a forked child does not have (a worker hung there in a test that had decoded before forking)."""
        INHERITED_DECODERS.append(self.episode_frames.cameras)
        self.episode_frames.cameras = {}

    def parts(self, episode: int, lo: int, hi: int) -> list[Tensor]:
        """Each key's frames ``lo … hi``, unjoined (cameras uint8 at the working resolution)."""
        return [self.episode_frames.read(key, episode, lo, hi) for key in self.keys]


class FrameTable:
    """A dataset's frames of several keys, stored apart and joined on request (``ObservationLayout.join``): cameras
    uint8 at the working resolution, memory-mapped from the frame cache (``data.frame_cache``), so that memory does
    not grow with the dataset; vectors float32 in memory. Indexed by dataset row."""

    def __init__(
        self, dataset: LeRobotDataset, keys: list[str], layout: ObservationLayout, video_backend: str, device=None
    ):
        self.layout, self.device = layout, device
        hf = dataset.hf_dataset
        bounds = episode_bounds(dataset.meta)
        index = column_array(hf, "index").astype(np.int64)
        self.length = len(index)
        shapes = layout_shapes(dataset.meta, keys, layout)
        self.parts, self.positions = [], []
        for key, visual in zip(keys, layout.visual, strict=True):
            if visual:
                self.parts.append(cached_frames(dataset, key, shapes[key], video_backend))
                self.positions.append(index - (bounds[0][0] if bounds else 0))
            else:
                self.parts.append(column_array(hf, key).astype(np.float32).reshape(self.length, -1))
                self.positions.append(None)

    def __len__(self) -> int:
        return self.length

    def vector_columns(self, rows: np.ndarray, columns: list[int]) -> np.ndarray:
        """Columns of vector keys of the joined frames of ``rows`` (any shape), float32, shaped ``rows.shape +
        (len(columns),)``, read without a camera frame: one gather per key."""
        rows = np.asarray(rows, dtype=np.int64)
        starts = np.cumsum([0, *self.layout.sizes])
        columns = np.asarray(columns, dtype=np.int64)
        part_of = np.searchsorted(starts, columns, side="right") - 1
        out = np.empty((rows.size, len(columns)), dtype=np.float32)
        for part in np.unique(part_of):
            if self.layout.visual[part]:
                column = columns[part_of == part][0]
                raise ValueError(f"column {column} of the joined frames is a camera's, not a vector key's")
            where = np.flatnonzero(part_of == part)
            out[:, where] = self.parts[part][np.ix_(rows.reshape(-1), columns[where] - starts[part])]
        return out.reshape(*rows.shape, len(columns))

    def packed_parts(self, rows: np.ndarray, parts: list[int]) -> Tensor:
        """The joined frames' values of keys ``parts`` (positions, in layout order) for ``rows`` (any shape), as
        ``self[rows][..., layout.indices(parts)]`` packs them, without reading or copying the other keys (a camera
        network's frames: the gather after a whole join copied every camera value twice)."""
        flat = np.asarray(rows, dtype=np.int64).reshape(-1)
        values = []
        for p in parts:
            where = self.positions[p]
            part = torch.from_numpy(np.ascontiguousarray(self.parts[p][flat if where is None else where[flat]]))
            values.append(resize_images(part, self.layout.shapes[p][1:]) if self.layout.visual[p] else part)
        out = pack_tensors(values, [self.layout.visual[p] for p in parts])
        out = out.reshape(*np.shape(rows), out.shape[1])
        return out if self.device is None else out.to(self.device)

    def __getitem__(self, rows) -> Tensor:
        """The joined frames of ``rows`` (any shape of row numbers), shaped ``rows.shape + frame``."""
        rows = np.asarray(rows.cpu() if torch.is_tensor(rows) else rows, dtype=np.int64)
        flat = rows.reshape(-1)
        parts = [
            torch.from_numpy(np.ascontiguousarray(part[flat if where is None else where[flat]]))
            for part, where in zip(self.parts, self.positions, strict=True)
        ]
        joined = torch.as_tensor(self.layout.join(parts))
        joined = joined.reshape(*rows.shape, *joined.shape[1:])
        return joined if self.device is None else joined.to(self.device)


def observation_array(
    dataset: LeRobotDataset, keys: str | list[str], video_backend: str = "pyav", layout: ObservationLayout | None = None
) -> np.ndarray:
    """Every frame's observation in dataset order, held in memory: float32 states, or uint8 (N, C, H, W) images;
    several keys are joined in key order (``ObservationLayout.join``). Cameras are read at ``layout``'s working
    resolution (default: as stored) through the frame cache."""
    keys = [keys] if isinstance(keys, str) else list(keys)
    layout = layout or dataset_layout(dataset.meta, keys)
    table = FrameTable(dataset, keys, layout, video_backend)
    return table[np.arange(len(table))].numpy()


def action_array(dataset: LeRobotDataset) -> np.ndarray:
    """The ``action`` column: int64 ids (N,) of a discrete action (integer dtype), else float32 (N, action_dim)."""
    actions = column_array(dataset.hf_dataset, ACTION)
    if np.issubdtype(actions.dtype, np.integer):
        return actions.reshape(-1).astype(np.int64)
    return actions.reshape(len(actions), -1).astype(np.float32)


def load_transitions(
    dataset: LeRobotDataset,
    keys: str | list[str],
    video_backend: str = "pyav",
    layout: ObservationLayout | None = None,
    context: int = 0,
) -> Transitions:
    """Every a_t of a dataset with actions that has a successor frame, with its window of ``context`` (frames
    t-k … t+1+k, clamped into its episode), in memory; images kept as uint8, cameras at ``layout``'s working
    resolution (default: as stored)."""
    episodes = column_array(dataset.hf_dataset, "episode_index")
    actions = action_array(dataset)
    states = observation_array(dataset, keys, video_backend, layout)
    starts = np.flatnonzero(np.r_[True, episodes[1:] != episodes[:-1]])
    lengths = np.diff(np.r_[starts, len(episodes)])
    first, last = np.repeat(starts, lengths), np.repeat(starts + lengths - 1, lengths)
    has_next = np.flatnonzero(np.arange(len(episodes)) < last)
    windows = window_indices(has_next, context_offsets(context), first[has_next], last[has_next])
    return Transitions(states[windows], actions[has_next])


def window_indices(t: np.ndarray, offsets: list[int], first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """(len(t), len(offsets)) indices t + offset, clamped into each row's episode [first, last] (inclusive): an
    episode's edges repeat its first or last frame."""
    t, first, last = np.asarray(t)[:, None], np.asarray(first)[:, None], np.asarray(last)[:, None]
    return np.clip(t + np.asarray(offsets, dtype=np.int64)[None, :], first, last)


def span_windows(frames: Tensor, span: LabelSpan, offsets: list[int], batch: int) -> list[Tensor]:
    """The windows (T, F, …) of ``span``'s frames t at consecutive ``offsets``, from its frames ``lo … hi``
    (``frames``, (n, …)), edges clamped as ``window_indices`` clamps them, in passes of at most ``batch`` windows:
    each a strided view of the frames, a pass that reaches a clamped edge a view of its own frames gathered. Gathering
    each window's frames wrote every frame F times: the IDM's passes on two 640×480 cameras took 14–24% longer
    (benchmarks/measure/span_windows.py); gathering a whole span wherever it touched an episode's edge, as the first
    version did, copied every frame of a short episode once."""
    if list(offsets) != list(range(offsets[0], offsets[0] + len(offsets))):
        raise ValueError(f"span_windows reads consecutive offsets, got {offsets}")
    rows = np.clip(np.arange(span.start + offsets[0], span.stop + offsets[-1]), span.first, span.last) - span.lo
    frames = frames.contiguous()
    size, count = frames[0].numel(), len(offsets)
    passes = []
    for first in range(0, span.stop - span.start, batch):
        windows = min(batch, span.stop - span.start - first)
        needed = rows[first : first + windows + count - 1]
        if needed[0] + len(needed) - 1 == needed[-1]:  # no edge repeated: the frames themselves
            padded = frames[needed[0] : needed[-1] + 1]
        else:
            padded = frames[torch.as_tensor(needed, device=frames.device)]
        passes.append(padded.as_strided((windows, count, *padded.shape[1:]), (size, size, *padded.stride()[1:])))
    return passes


class ExpertFrames:
    """The expert dataset at hand (``FrameTable``: vectors in memory, cameras memory-mapped at the working
    resolution), so that a training batch needs only its frames' ``index`` from LeRobot's loader: with
    ``delta_timestamps`` for s_{t+1} its per-item cost is 12× higher (1.04 vs 0.08 ms measured on a vector dataset)
    and that loading was 70–85% of a vector training run."""

    def __init__(
        self,
        dataset: LeRobotDataset,
        keys: str | list[str],
        with_actions: bool,
        device: torch.device,
        layout: ObservationLayout | None = None,
        video_backend: str = "pyav",
    ):
        index = column_array(dataset.hf_dataset, "index").astype(np.int64)
        self.row_of_index = np.full(int(index.max()) + 1, -1, dtype=np.int64)
        self.row_of_index[index] = np.arange(len(index))
        self.episodes = column_array(dataset.hf_dataset, "episode_index").astype(np.int64)
        starts = np.flatnonzero(np.r_[True, self.episodes[1:] != self.episodes[:-1]])
        ends = np.r_[starts[1:], len(self.episodes)] - 1
        lengths = ends - starts + 1
        self.first_row, self.last_row = np.repeat(starts, lengths), np.repeat(ends, lengths)
        keys = [keys] if isinstance(keys, str) else list(keys)
        self.keys = keys
        self.states = FrameTable(dataset, keys, layout or dataset_layout(dataset.meta, keys), video_backend, device)
        self.actions = torch.as_tensor(action_array(dataset), device=device) if with_actions else None

    def rows(self, frame_index: Tensor) -> np.ndarray:
        """Rows of the batch's frames (LeRobot's ``index`` column: absolute frame numbers)."""
        index = frame_index.detach().cpu().numpy().reshape(-1).astype(np.int64)
        known = (index >= 0) & (index < len(self.row_of_index))
        rows = np.where(known, self.row_of_index[np.clip(index, 0, len(self.row_of_index) - 1)], -1)
        if (rows < 0).any():
            raise KeyError("the batch holds frame indices that are not in the expert dataset")
        return rows

    def windows(self, rows: np.ndarray, offsets: list[int]) -> Tensor:
        """Frames (B, len(offsets), …) at ``offsets`` around each row, clamped into its episode."""
        return self.states[window_indices(rows, offsets, self.first_row[rows], self.last_row[rows])]

    def part_windows(self, rows: np.ndarray, offsets: list[int], parts: list[int]) -> Tensor:
        """Keys ``parts``' packed values (B, len(offsets), values) at ``offsets`` around each row (``packed_parts``)."""
        return self.states.packed_parts(window_indices(rows, offsets, self.first_row[rows], self.last_row[rows]), parts)

    def column_windows(self, rows: np.ndarray, offsets: list[int], columns: list[int]) -> np.ndarray:
        """Vector ``columns`` of the joined frames (B, len(offsets), len(columns)) at ``offsets`` around each row,
        clamped into its episode, read without a camera frame."""
        index = window_indices(rows, offsets, self.first_row[rows], self.last_row[rows])
        return self.states.vector_columns(index, columns)

    def vector_windows(self, key: str, rows: np.ndarray, offsets: list[int]) -> Tensor:
        """One vector key's values (B, len(offsets), D) at ``offsets`` around each row, clamped into its episode."""
        # A whole key in one fancy index, not through column_windows: a training step's windows, where that path's
        # bookkeeping took 4x as long (121 against 31 µs for 64 windows of 12 frames × 26 joints).
        values = self.states.parts[self.keys.index(key)]
        index = window_indices(rows, offsets, self.first_row[rows], self.last_row[rows])
        windows = torch.from_numpy(np.ascontiguousarray(values[index]))
        return windows if self.states.device is None else windows.to(self.states.device)

    def transition_windows(self, rows: np.ndarray, offsets: list[int]) -> Tensor:
        """Frames (B, len(offsets), …) around rows that have a successor; LeRobot's sampler never draws an episode's
        last frame (``drop_n_last_frames = 1``)."""
        if rows.max() + 1 >= len(self.episodes) or (self.episodes[rows] != self.episodes[rows + 1]).any():
            raise ValueError("a batch frame is the last of its episode (it has no successor)")
        return self.windows(rows, offsets)

    def pairs(self, rows: np.ndarray) -> tuple[Tensor, Tensor]:
        """(s_t, s_{t+1}) of rows that have a successor (``transition_windows``)."""
        state, next_state = self.transition_windows(rows, [0, 1]).unbind(1)
        return state, next_state
