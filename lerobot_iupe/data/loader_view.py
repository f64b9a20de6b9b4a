"""What ``lerobot-train``'s loader reads for a policy that takes its frames from the package's own cache by the
batch's ``index``: every column except the cameras.

LeRobot 0.6.1's ``DatasetReader.get_item`` decodes every camera of ``meta.video_keys`` (and every PNG column) for
each item, whatever the policy consumes, and offers no option to choose (``delta_timestamps=[]`` for a camera
crashes on an empty stack). A reading view of the metadata without the cameras does it: the dataset keeps its own
metadata (the policy, the processors and the checkpoint see every feature), only its reader stops decoding, and
its items carry an empty placeholder for each camera. LeRobot's own proposal for the same need works this way
(dropping camera features from the metadata of a dataset opened for reading); here the view is given to one
reader only, so nothing written or shared sees it.
"""

from __future__ import annotations

import copy
import dataclasses
import logging

import torch
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.io_utils import hf_transform_to_torch

log = logging.getLogger("lerobot_iupe")


class ReaderWithoutCameras(DatasetReader):
    """LeRobot's reader of one dataset, reading by a view of its metadata without the cameras: they are not
    decoded, and each item holds an empty placeholder (0,) uint8 under each camera's key, so that a batch keeps
    LeRobot's keys (its processors want an observation, and a maze's is a camera alone)."""

    cameras: tuple[str, ...] = ()

    @classmethod
    def from_reader(cls, reader: DatasetReader, cameras: list[str]) -> ReaderWithoutCameras:
        # A copy of the reader's state (its loaded table, index mapping, delta indices): nothing is reloaded.
        lean = object.__new__(cls)
        lean.__dict__.update(reader.__dict__)
        meta = reader._meta  # the one attribute get_item reads the cameras by (video_keys, camera_keys)
        lean._meta = copy.copy(meta)
        lean._meta.info = dataclasses.replace(
            meta.info, features={k: v for k, v in meta.features.items() if k not in cameras}
        )
        lean.cameras = tuple(cameras)
        stored_images = [k for k in cameras if k in lean.hf_dataset.column_names]
        if stored_images:  # PNG columns are decoded by the table's row access itself: drop them from this table
            lean.hf_dataset = lean.hf_dataset.remove_columns(stored_images)
            lean.hf_dataset.set_transform(hf_transform_to_torch)
        return lean

    def get_item(self, idx) -> dict:
        item = super().get_item(idx)
        for key in self.cameras:
            item[key] = torch.zeros(0, dtype=torch.uint8)
        return item


def stop_decoding_cameras(dataset) -> list[str]:
    """Give ``dataset`` (a ``LeRobotDataset`` about to feed ``lerobot-train``'s loader) a reader that decodes none
    of its cameras (``ReaderWithoutCameras``); the cameras. Other datasets (streaming, several datasets) and readers
    of another LeRobot layout are left as they are, with a warning: they decode as before."""
    if not isinstance(dataset, LeRobotDataset):
        log.warning(f"IUPE: lerobot-train's loader decodes every camera of a {type(dataset).__name__} (unchanged)")
        return []
    cameras = dataset.meta.camera_keys  # video and PNG image features alike
    if not cameras:
        return []
    reader = dataset._ensure_reader()
    if type(reader) is not DatasetReader or reader.hf_dataset is None:
        log.warning("IUPE: this LeRobot's dataset reader is not the one known; its loader decodes every camera")
        return []
    dataset.reader = ReaderWithoutCameras.from_reader(reader, cameras)
    return cameras
