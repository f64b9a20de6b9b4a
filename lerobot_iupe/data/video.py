"""Camera frames at the policy's working resolution: one resize rule (bilinear, antialiased) for frames already in
memory (``resize_images``), and the video decoder's own scaler for frames read from a dataset (``CameraFrames``), so
that a 640×480 frame is never held, converted or copied at full size.

Frames scaled to a working resolution are decoded by PyAV whatever the backend, converted to RGB and scaled in
one pass of FFmpeg's scaler (``frame.reformat``), on one thread. Per 640×480 AV1 frame on one core: 2.07 ms,
against 2.68 for torchcodec's ``Resize`` (RGB at full size, then scaled: 2.58 ms through PyAV), 2.43 for
torchcodec's full-size decode and 1.92 for PyAV's (benchmarks/speed.md). The two rules give frames 1.1–1.4 levels
apart on average (torchcodec's is within 0.02 of ``resize_images``); training's frame cache and relabelling read
the same decoder, so the IDM labels the frames it was trained on. Frames at the stored size come from the backend
asked for (torchcodec's 1.2–1.5× PyAV's frames/s on 64×64 maze episodes).
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812
from torch import Tensor


def resize_images(images, shape: tuple[int, int] | list[int]):
    """Images (N, C, H, W) — uint8 0–255 or float 0–1, numpy or torch — at (h, w) = ``shape``, same type and dtype;
    unchanged when they already have it."""
    h, w = int(shape[0]), int(shape[1])
    if tuple(images.shape[-2:]) == (h, w):
        return images
    as_numpy = isinstance(images, np.ndarray)
    tensor = torch.from_numpy(images) if as_numpy else images
    resized = F.interpolate(tensor.float(), size=(h, w), mode="bilinear", antialias=True, align_corners=False)
    if tensor.dtype == torch.uint8:
        resized = resized.round_().clamp_(0, 255).to(torch.uint8)
    else:
        resized = resized.to(tensor.dtype)
    return resized.numpy() if as_numpy else resized


def working_shape(height: int, width: int, longest_side: int) -> tuple[int, int]:
    """(h, w) with the aspect ratio of (height, width) and the longer side at most ``longest_side``."""
    scale = min(1.0, longest_side / max(height, width))
    return max(1, round(height * scale)), max(1, round(width * scale))


def open_video(path: Path | str):
    """A video file opened by PyAV to decode on one thread, so that processes scale out over the cores: ``thread_type``
    alone does not reach libdav1d, which starts a thread per core unless ``thread_count`` is set."""
    import av

    container = av.open(str(path))
    stream = container.streams.video[0]
    stream.thread_type = "NONE"
    stream.codec_context.thread_count = 1
    return container


def default_video_backend() -> str:
    """LeRobot's rule (torchcodec where it loads, else pyav), minus its page-long traceback when it does not."""
    from lerobot.utils.import_utils import get_safe_default_video_backend

    logger = logging.getLogger("lerobot.utils.import_utils")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        return get_safe_default_video_backend()
    finally:
        logger.setLevel(level)


class CameraFrames:
    """Frame ranges of one episode of a dataset's video cameras, decoded at ``shape`` (h, w) (None: as stored), as
    uint8 (n, C, h, w). Open decoders are kept per file (an episode is a stretch of a file shared with others), so
    that consecutive ranges do not reopen it. Meant for one thread or process at a time."""

    OPEN_FILES = 4

    def __init__(self, meta, backend: str, shape: tuple[int, int] | None):
        self.meta, self.backend = meta, backend
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))
        self._decoders: OrderedDict[Path, object] = OrderedDict()

    def frames(self, key: str, episode: int, lo: int, hi: int) -> Tensor:
        """Frames ``lo … hi`` (global indices, inclusive) of ``episode``'s video of camera ``key``."""
        meta = self.meta
        first = int(meta.episodes[episode]["dataset_from_index"])
        offset = float(meta.episodes[episode][f"videos/{key}/from_timestamp"])
        path = meta.root / meta.get_video_file_path(episode, key)
        start_s = offset + (lo - first) / meta.fps
        count = hi - lo + 1
        stored = tuple(int(v) for v in meta.features[key]["shape"][:2])
        if self.decoder_name(self.backend, self.shape, stored) == "torchcodec":
            frames = self._torchcodec(path, start_s, count)
        else:
            frames = self._pyav(path, start_s, count)
        if len(frames) != count:
            raise RuntimeError(
                f"{path}: expected {count} frames from {start_s:.3f} s (episode {episode}, frames {lo}…{hi}) but the "
                f"video holds {len(frames)} there; the dataset's episode timestamps and its video disagree (a "
                f"recording whose streaming encoder fell behind drops frames: 'Encoder queue full' at record time). "
                f"Re-record that episode or remove it from the dataset"
            )
        return frames

    def _decoder(self, path: Path, make):
        decoder = self._decoders.pop(path, None) or make()
        self._decoders[path] = decoder
        while len(self._decoders) > self.OPEN_FILES:
            _, old = self._decoders.popitem(last=False)
            if hasattr(old, "close"):
                old.close()
        return decoder

    @staticmethod
    def decoder_name(backend: str, shape: tuple[int, int] | None, stored: tuple[int, int]) -> str:
        """What decodes frames stored at ``stored`` (h, w) read at ``shape`` with ``backend`` (a frame cache is
        named by it): the backend at the stored size, PyAV's scaler at any other."""
        return backend if shape is None or tuple(shape) == tuple(stored) else "pyav, one bilinear pass to RGB"

    def _torchcodec(self, path: Path, start_s: float, count: int) -> Tensor:
        from torchcodec.decoders import VideoDecoder

        decoder = self._decoder(path, lambda: VideoDecoder(str(path), num_ffmpeg_threads=1))
        first = round(start_s * decoder.metadata.average_fps)
        last = min(first + count, decoder.metadata.num_frames)
        return decoder.get_frames_in_range(first, last).data

    def _pyav(self, path: Path, start_s: float, count: int) -> Tensor:
        container = self._decoder(path, lambda: open_video(path))
        stream = container.streams.video[0]
        tolerance = 0.5 / self.meta.fps
        container.seek(max(0, int((start_s - tolerance) / stream.time_base)), stream=stream, backward=True)
        frames = []
        for frame in container.decode(stream):
            if frame.time is None or frame.time < start_s - tolerance:
                continue
            if self.shape:
                frame = frame.reformat(
                    width=self.shape[1], height=self.shape[0], format="rgb24", interpolation="BILINEAR"
                )
                frames.append(frame.to_ndarray())
            else:
                frames.append(frame.to_ndarray(format="rgb24"))
            if len(frames) == count:
                break
        if not frames:
            return torch.empty(0, 3, *(self.shape or (0, 0)), dtype=torch.uint8)
        return torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2).contiguous()
