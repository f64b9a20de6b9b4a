"""The IDM's labelling passes with each window's frames gathered (the code before ``readers.span_windows``) against
the windows as a strided view of the span's frames, alternating on the same decoded spans in one process, one thread;
the outputs are compared to the bit.

    python benchmarks/measure/span_windows.py --policy outputs/speed/ckpt-camera/checkpoints/last/pretrained_model \
        --dataset outputs/speed/arm-2000 [--spans 6] [--rounds 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.readers import FrameReader, episode_bounds, label_spans, window_indices
from lerobot_iupe.policy import IUPEPolicy
from lerobot_iupe.relabel.labelling import IDM_BATCH, labelling_pass, span_outputs


def gathered_outputs(policy: IUPEPolicy, reader: FrameReader, span, parts) -> torch.Tensor:
    """The labelling passes as they were: every window's frames gathered, pass by pass."""
    frames = reader.layout.join(parts)
    t = np.arange(span.start, span.stop)
    index = window_indices(t, policy.config.idm_window, np.full(len(t), span.first), np.full(len(t), span.last))
    passes = torch.as_tensor(index - span.lo).split(IDM_BATCH)
    return torch.cat([labelling_pass(policy, frames[part]) for part in passes])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="a checkpoint's pretrained_model directory")
    parser.add_argument("--dataset", required=True, help="a local LeRobot dataset the checkpoint reads")
    parser.add_argument("--spans", type=int, default=6)
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = IUPEPolicy.from_pretrained(args.policy).eval()
    dataset = LeRobotDataset("local/span-windows", root=args.dataset)
    keys = policy.labelling_keys
    reader = FrameReader(dataset, keys, policy.config.layout_of(keys), "torchcodec")
    spans = label_spans(episode_bounds(dataset.meta), 256, policy.config.idm_window)[: args.spans]
    seconds = {"gathered": 0.0, "view": 0.0}
    identical = True
    with torch.no_grad():
        for span in spans:
            parts = reader.parts(span.episode, span.lo, span.hi)
            for _ in range(args.rounds):
                start = time.perf_counter()
                before = gathered_outputs(policy, reader, span, parts)
                seconds["gathered"] += time.perf_counter() - start
                start = time.perf_counter()
                after = span_outputs(policy, reader, span, parts, "cpu")
                seconds["view"] += time.perf_counter() - start
                identical &= torch.equal(before, after)
    windows = sum(span.stop - span.start for span in spans) * args.rounds
    print(f"{windows} windows: gathered {seconds['gathered']:.2f} s, view {seconds['view']:.2f} s; "
          f"outputs identical: {identical}")  # fmt: skip


if __name__ == "__main__":
    main()
