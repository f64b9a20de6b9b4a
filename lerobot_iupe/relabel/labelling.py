"""The IDM's labels of every frame with a successor, span by span: decoded and labelled by worker processes that
take whole episodes (one per core), in one process, or split among several (``torchrun``). The labels of an
episode do not depend on which process labels it."""

from __future__ import annotations

import copy
import gc
import multiprocessing as mp
import os
import traceback
from queue import Empty

import numpy as np
import torch
import torch.distributed as dist
from lerobot.datasets import LeRobotDatasetMetadata
from tqdm.auto import tqdm

from lerobot_iupe.data.child_processes import exit_with_parent
from lerobot_iupe.data.readers import FrameReader, LabelSpan, episode_bounds, span_windows
from lerobot_iupe.policy import IUPEPolicy

# Windows per IDM forward pass, whatever --batch_size (the decoding span) is: an image IDM's activations and
# attention maps for a few dozen windows stay in the CPU's cache; passes of a whole maze episode (133 windows)
# labelled 1.5× slower (benchmarks/relabel.md).
IDM_BATCH = 32
LAST_FRAME_RULE = "repeats the label of the frame before it (0 for a one-frame episode)"


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, as a container or ``taskset`` sets it)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def span_outputs(
    policy: IUPEPolicy, reader: FrameReader, span: LabelSpan, parts: list, device: str, references: bool = True
) -> torch.Tensor:
    """The IDM's outputs (float32, on the CPU) for the frames of ``span``, whose decoded keys are ``parts``, with
    the references after them when ``references`` (``labelling_pass``)."""
    passes = span_windows(reader.layout.join(parts).to(device), span, policy.config.idm_window, IDM_BATCH)
    return torch.cat([labelling_pass(policy, window, references) for window in passes])


def labelling_pass(policy: IUPEPolicy, window: torch.Tensor, references: bool = True) -> torch.Tensor:
    """The IDM's outputs of one pass; after them ride, when ``references`` (a dataset with actions to compare
    them with), the report's references (``assemble_references``), from the frames already decoded: the camera
    dimensions' thumbnail ridge, or the linear part of an IDM that has one."""
    output = policy.labelling_output(window)
    if references and policy.config.camera_dims:
        output = torch.cat([output, policy.camera_reference(window).to(output.dtype)], dim=-1)
    elif references and policy.idm_prior is not None and policy.idm_prior.is_fitted:  # the IDM's ridge alone
        output = torch.cat([output, policy.idm_prior(window).to(output.dtype)], dim=-1)
    return output.float().cpu()


def _work(
    policy, reader: FrameReader, spans: dict, tasks, out, device: str | None, parent_pid: int, references: bool
) -> None:
    """A worker process: episodes from ``tasks`` until None, each span's IDM outputs into ``out`` in the episode's
    order (``device`` None: its decoded frames, for the first process's IDM), then None. It dies with its parent."""
    exit_with_parent(parent_pid)
    # One thread: the first process's, when these workers label (the same sums, the same labels); a forked child
    # must not start a thread pool (torch's DataLoader workers do the same).
    torch.set_num_threads(1)
    reader.forget_open_files()
    try:
        while (episode := tasks.get()) is not None:
            for span in spans[episode]:
                parts = reader.parts(span.episode, span.lo, span.hi)
                if device is None:
                    out.put((span, [p.numpy() for p in parts]))
                else:
                    out.put((span, span_outputs(policy, reader, span, parts, device, references).numpy()))
        out.put(None)
    except BaseException:
        out.put(traceback.format_exc())


def outputs_in_workers(
    policy: IUPEPolicy,
    reader: FrameReader,
    spans: list[LabelSpan],
    workers: int,
    device: str,
    label_in_workers: bool | None = None,
    references: bool = True,
):
    """(span, IDM outputs) for every span, each episode's spans in order, episodes in the order they finish.
    ``workers`` processes take whole episodes from a queue and decode them; on the CPU they also run the IDM
    (one per core: a labeller in this process alone would bound the rate at one core's), on a GPU this process
    does, and so does a CPU labeller of several threads (``label_in_workers``, default: a CPU labeller of one
    thread). Forked where the OS can (Linux; as
    torch's DataLoader forks its workers): a spawned process would spend ~4 s importing torch and LeRobot first."""
    context = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    by_episode: dict[int, list[LabelSpan]] = {}
    for span in spans:
        by_episode.setdefault(span.episode, []).append(span)
    workers = max(1, min(workers, len(by_episode)))
    tasks, out = context.Queue(), context.Queue(maxsize=2 * workers)  # bounded: memory follows the workers
    for episode in by_episode:
        tasks.put(episode)
    for _ in range(workers):
        tasks.put(None)
    if label_in_workers is None:  # a labeller of several threads stays here: a forked child must not start a pool
        label_in_workers = device == "cpu" and torch.get_num_threads() == 1
    label_here = not label_in_workers
    args = (policy, reader, by_episode, tasks, out, None if label_here else device, os.getpid(), references)
    processes = [context.Process(target=_work, args=args, daemon=True) for _ in range(workers)]
    # Frozen objects are never collected: a child's garbage collector would otherwise free decoders the parent had
    # dropped, and freeing an AV1 decoder without its threads hangs.
    gc.freeze()
    try:
        for process in processes:
            process.start()
    finally:
        gc.unfreeze()
    try:
        running = workers
        while running:
            item = _next_decoded(out, processes)
            if item is None:
                running -= 1
            elif isinstance(item, str):
                raise RuntimeError(f"decoding the dataset's frames failed:\n{item}")
            else:
                span, result = item
                if label_here:
                    parts = [torch.from_numpy(p) for p in result]
                    result = span_outputs(policy, reader, span, parts, device, references)
                    yield span, result
                else:
                    yield span, torch.from_numpy(result)
    finally:
        for process in processes:
            process.kill()
            process.join()


def outputs_in_process(
    policy: IUPEPolicy, reader: FrameReader, spans: list[LabelSpan], device: str, references: bool = True
):
    """(span, IDM outputs) for every span in order, decoded and labelled in this process (``--num_workers=0``)."""
    for span in spans:
        parts = reader.parts(span.episode, span.lo, span.hi)
        yield span, span_outputs(policy, reader, span, parts, device, references)


def _next_decoded(queue, processes: list):
    """The workers' next item; an error if one died without saying why (killed, e.g. out of memory)."""
    while True:
        try:
            return queue.get(timeout=5)
        except Empty:
            for process in processes:
                if process.exitcode not in (None, 0):
                    raise RuntimeError(
                        f"a process decoding the dataset's frames died (exit code {process.exitcode}); if it was "
                        "killed for memory, lower --batch_size or --num_workers"
                    ) from None


def episode_generator(seed: int, episode: int) -> torch.Generator:
    """The draws of one episode (``--mode=sample``): the same whichever process labels it."""
    return torch.Generator().manual_seed(seed * 1_000_003 + episode)


@torch.no_grad()
def label_spans_with_idm(
    policy: IUPEPolicy,
    reader: FrameReader,
    spans: list[LabelSpan],
    mode: str,
    seed: int,
    device: str = "cpu",
    progress: bool = True,
    workers: int = 0,
    references: bool = True,
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Labels (int64 ids, or float32 vectors) and confidences (the IDM's probability of its label, or its std per
    dimension in units of the action range) of the frames of ``spans``, by episode; each
    episode's last frame follows ``LAST_FRAME_RULE``. Decoded (and on the CPU labelled) by ``workers`` processes
    (``outputs_in_workers``), or in this one (0); the labels are the same either way: an episode's spans are
    labelled in order, with the episode's own draws. ``references``: the report's references ride along (third
    item), for a dataset whose actions they are compared with."""
    # Labels are chosen on the CPU from the IDM's outputs, whatever device it runs on: the episode's generator is a
    # CPU one, and a CUDA IDM then labels as the CPU one does.
    config, head = policy.config, copy.deepcopy(policy.idm_head).cpu()
    width = head.out_features  # the outputs' own columns; any after them are references (``labelling_pass``)
    results: dict[int, tuple[list, list, list]] = {}
    generators: dict[int, torch.Generator] = {}
    if workers:
        outputs = outputs_in_workers(policy, reader, spans, workers, device, references=references)
    else:
        outputs = outputs_in_process(policy, reader, spans, device, references)

    total = sum(span.stop - span.start for span in spans)
    with tqdm(total=total, desc="relabel", unit="frame", unit_scale=True, disable=not progress) as bar:
        for span, output in outputs:
            output, reference = output[:, :width], output[:, width:]
            generator = generators.setdefault(span.episode, episode_generator(seed, span.episode))
            chosen = head.choose(output, mode == "sample", generator)
            if config.is_continuous:
                _, std = head.mean_and_std(output)
                confidence = 0.5 * std  # per dimension, in units of the action range (scaled space spans 2)
            else:
                confidence = head.likelihood(output, chosen)
            labels, confidences, references = results.setdefault(span.episode, ([], [], []))
            labels.append(chosen.numpy())
            confidences.append(confidence.numpy())
            references.append(reference.numpy())
            bar.update(span.stop - span.start)
    return {episode: tuple(np.concatenate(part) for part in parts) for episode, parts in results.items()}


def in_frame_order(per_episode: dict[int, tuple], bounds: list[tuple[int, int]], item: int, out: np.ndarray):
    """``out`` (one row per frame from ``bounds``' first) with item ``item`` of each labelled episode's tuple written
    at the episode's frames that have a successor (the last one has no window); other rows are left as they are."""
    base = bounds[0][0] if bounds else 0
    for episode, (first, end) in enumerate(bounds):
        if episode in per_episode:
            rows = out[first - base : end - 1 - base]
            rows[...] = per_episode[episode][item].reshape(rows.shape)
    return out


def assemble_labels(
    per_episode: dict[int, tuple[np.ndarray, np.ndarray]], bounds: list[tuple[int, int]], config
) -> tuple[np.ndarray, np.ndarray]:
    """One label per frame of the dataset, in frame order (the last frame of an episode: ``LAST_FRAME_RULE``)."""
    frames = (bounds[-1][1] - bounds[0][0]) if bounds else 0
    shape = (frames, config.action_dim) if config.is_continuous else (frames,)
    labels = in_frame_order(per_episode, bounds, 0, np.zeros(shape, np.float32 if config.is_continuous else np.int64))
    confidence = in_frame_order(per_episode, bounds, 1, np.zeros(shape, np.float32))
    base = bounds[0][0] if bounds else 0
    for first, end in bounds:
        if end - first > 1:
            labels[end - 1 - base] = labels[end - 2 - base]
            confidence[end - 1 - base] = confidence[end - 2 - base]
    return labels, confidence


def assemble_references(per_episode: dict[int, tuple], bounds: list[tuple[int, int]]) -> np.ndarray | None:
    """The references that rode along with the labels (``labelling_pass``), one row per frame in frame order (an
    episode's last frame, which has no window, NaN); None without any."""
    widths = {parts[2].shape[-1] for parts in per_episode.values()}
    if not widths or widths == {0}:
        return None
    frames = bounds[-1][1] - bounds[0][0]
    return in_frame_order(per_episode, bounds, 2, np.full((frames, max(widths)), np.nan, dtype=np.float32))


def last_frame_mask(meta: LeRobotDatasetMetadata, total_frames: int) -> np.ndarray:
    mask = np.zeros(total_frames, dtype=bool)
    mask[[end - 1 for _, end in episode_bounds(meta)]] = True
    return mask


def process_group() -> tuple[int, int]:
    """(rank, world size): under ``torchrun``/Accelerate (WORLD_SIZE > 1) a gloo process group is joined."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank(), dist.get_world_size()) if dist.is_initialized() else (0, 1)


def gather_on_first(per_episode: dict, world: int) -> dict | None:
    """Every process's labels on process 0 (None elsewhere)."""
    if world == 1:
        return per_episode
    gathered = [None] * world if dist.get_rank() == 0 else None
    dist.gather_object(per_episode, gathered, dst=0)
    if gathered is None:
        return None
    return {episode: labels for part in gathered for episode, labels in part.items()}
