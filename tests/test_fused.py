"""Cameras and state together, on datasets written by LeRobot's own writer (no package metadata): each action
dimension shows in one input only — the first in the top camera, the second in the side camera, the third in
observation.state — so an IDM that drops any of them cannot label that dimension. (Cameras as PNG frames at
16×16, which keeps training short; LeRobot's AV1 video encoder needs larger frames, and the video path is
tested in test_relabel_any.)"""

import json
import shutil

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, once, run_in_process
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_iupe.data.readers import column_array
from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.algorithm import r_squared
from lerobot_iupe.policy.modeling_iupe import IUPEPolicy

TOP, SIDE = "observation.images.top", "observation.images.side"
SIZE = 16


def write_three_views(root, episodes: int, seed: int, with_actions: bool, order=(TOP, SIDE, OBS_STATE)) -> np.ndarray:
    """Three hidden levels p, each moved by one action dimension (p += 0.05 a); the top camera's grey level shows
    p[0], the side camera's p[1], observation.state holds p[2] and a distractor. Features are declared in
    ``order``. Returns every frame's true action (N, 3)."""
    rng = np.random.default_rng(seed)
    specs = {
        TOP: {"dtype": "image", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
        SIDE: {"dtype": "image", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]},
        OBS_STATE: {"dtype": "float32", "shape": (2,), "names": ["level", "distractor"]},
    }
    features = {key: specs[key] for key in order}
    if with_actions:
        features[ACTION] = {"dtype": "float32", "shape": (3,), "names": ["top", "side", "state"]}
    dataset = LeRobotDataset.create(f"local/{root.name}", 10, features, root=root, use_videos=False)
    actions = []
    for _ in range(episodes):
        levels = rng.uniform(0.3, 0.7, 3)
        for _ in range(int(rng.integers(20, 30))):
            action = rng.uniform(-1, 1, 3).astype(np.float32)
            grey = lambda level: np.full((SIZE, SIZE, 3), round(255 * (0.1 + 0.8 * level)), dtype=np.uint8)  # noqa: E731
            frame = {
                TOP: grey(levels[0]),
                SIDE: grey(levels[1]),
                OBS_STATE: np.array([levels[2], rng.normal()], dtype=np.float32),
                "task": "move the levels",
            }
            if with_actions:
                frame[ACTION] = action
            dataset.add_frame(frame)
            actions.append(action)
            levels = np.clip(levels + 0.05 * action, 0.0, 1.0)
        dataset.save_episode()
    dataset.finalize()
    return np.asarray(actions)


def inner(actions: np.ndarray, dataset) -> np.ndarray:
    episodes = column_array(dataset.hf_dataset, "episode_index")
    return actions[np.append(episodes[:-1] == episodes[1:], False)]


def labels_of(root) -> tuple[np.ndarray, LeRobotDataset]:
    dataset = LeRobotDataset(f"local/{root.name}", root=root, video_backend="pyav")
    return column_array(dataset.hf_dataset, ACTION), dataset


@pytest.fixture(scope="session")
def fused_idm(shared_dir):
    """A supervised IDM on every input of 16 labelled three-view episodes (built once for every worker)."""
    work = shared_dir / "fused"
    labelled = work / "labelled"

    def make():
        for leftover in (labelled, work / "idm"):
            shutil.rmtree(leftover, ignore_errors=True)
        write_three_views(labelled, episodes=16, seed=0, with_actions=True)
        run_in_process(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", "--policy.idm_context=0",
            f"--dataset.repo_id=local/{labelled.name}", f"--dataset.root={labelled}", "--dataset.video_backend=pyav",
            f"--output_dir={work / 'idm'}", "--num_workers=0", "--policy.device=cpu", "--wandb.enable=false",
            "--steps=150", "--save_freq=150", "--batch_size=64", "--policy.optimizer_lr=3e-3",
            "--policy.torch_threads=1", check=True
        )  # fmt: skip

    return once(work / "idm", make, CHECKPOINT) / CHECKPOINT, work


def relabel(checkpoint, root):
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{root.name}",
        f"--dataset.root={root}", "--dataset.video_backend=pyav",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]


def test_a_fused_idm_labels_what_only_one_camera_or_the_state_shows(fused_idm):
    checkpoint, work = fused_idm
    config = json.loads((checkpoint / "config.json").read_text())
    assert config["observation_keys"] == [TOP, SIDE, OBS_STATE]
    held_out, shuffled = work / "held-out", work / "held-out-shuffled"
    for leftover in (held_out, shuffled):
        shutil.rmtree(leftover, ignore_errors=True)
    true = write_three_views(held_out, episodes=6, seed=1, with_actions=False)
    relabel(checkpoint, held_out)
    labels, dataset = labels_of(held_out)
    per_dimension = [r_squared(inner(labels, dataset)[:, [d]], inner(true, dataset)[:, [d]]) for d in range(3)]
    assert min(per_dimension) > 0.8, per_dimension  # top camera, side camera, state

    # The same recording with its features declared in another order: the checkpoint's order decides.
    write_three_views(shuffled, episodes=6, seed=1, with_actions=False, order=(OBS_STATE, SIDE, TOP))
    relabel(checkpoint, shuffled)
    np.testing.assert_array_equal(labels_of(shuffled)[0], labels)


def fused_policy(**settings) -> IUPEPolicy:
    camera = PolicyFeature(type=FeatureType.VISUAL, shape=(3, 8, 8))
    state = PolicyFeature(type=FeatureType.STATE, shape=(2,))
    config = IUPEConfig(
        input_features={TOP: camera, SIDE: camera, OBS_STATE: state},
        action_low=[-1.0] * 3, action_high=[1.0] * 3, action_names=["a", "b", "c"], device="cpu", **settings,
    )  # fmt: skip
    torch.manual_seed(0)
    return IUPEPolicy(config)


@pytest.mark.parametrize("shared", [False, True])
def test_the_policy_reads_every_camera_and_the_state(shared):
    policy = fused_policy(shared_camera_encoder=shared)
    encoders = policy.pm_encoder.camera_encoders
    assert len(encoders) == (1 if shared else 2)
    for module in policy.modules():  # SAGAN's γ starts at 0; any value shows whether an input reaches the output
        if hasattr(module, "gamma"):
            module.gamma.data.fill_(0.5)
    generator = torch.Generator().manual_seed(1)
    batch = {
        TOP: torch.rand(4, 3, 8, 8, generator=generator),
        SIDE: torch.rand(4, 3, 8, 8, generator=generator),
        OBS_STATE: torch.randn(4, 2, generator=generator),
    }

    def outputs(batch):
        observation = policy.observation(batch)
        return policy.pm_history_output(observation[:, None]), policy.idm_output(observation, observation.flip(0))

    base = outputs(batch)
    for key in batch:
        changed = outputs({**batch, key: batch[key] + 0.5})
        for before, after in zip(base, changed, strict=True):
            assert not torch.allclose(before, after), f"{key} does not reach the output"


def test_the_idm_reads_only_its_keys():
    policy = fused_policy(idm_observation_keys=[OBS_STATE])
    observation = policy.observation(
        {TOP: torch.rand(2, 3, 8, 8), SIDE: torch.rand(2, 3, 8, 8), OBS_STATE: torch.ones(2, 2)}
    )
    blank = observation.clone()
    blank[:, : 2 * 3 * 8 * 8] = 0.0  # both cameras
    torch.testing.assert_close(policy.idm_output(observation, observation), policy.idm_output(blank, blank))
    assert not torch.allclose(policy.pm_history_output(observation[:, None]), policy.pm_history_output(blank[:, None]))


@pytest.mark.parametrize("context", [0, 2])
def test_the_fused_idm_reads_each_keys_frame_and_its_differences_as_the_general_path_packs_them(context):
    """The fused IDM cuts its input per key while it takes the differences (``_fused_difference_parts``); what it
    reads must be what the general path builds: [s_t, s_j − s_t …] of the normalised frames, packed flat."""
    policy = fused_policy(idm_context=context, joint_state_columns=[]).eval()
    assert not policy.config.joint_idm
    for module in policy.modules():
        if hasattr(module, "gamma"):
            module.gamma.data.fill_(0.5)
    policy.state_mean.copy_(torch.arange(policy.layout.size, dtype=torch.float32) * 0.01)
    policy.state_std.copy_(1.0 + torch.arange(policy.layout.size, dtype=torch.float32) * 0.02)
    policy.state_mean[: 2 * 3 * 8 * 8], policy.state_std[: 2 * 3 * 8 * 8] = 0.0, 1.0  # cameras are not normalised
    generator = torch.Generator().manual_seed(2)
    frames = 2 * context + 2
    window = torch.rand(5, frames, policy.layout.size, generator=generator)
    window[..., -2:] = torch.randn(5, frames, 2, generator=generator) * 3
    prepared = policy._prepare(window)
    now = prepared[:, context : context + 1]
    others = torch.cat([prepared[:, :context], prepared[:, context + 1 :]], dim=1)
    packed = torch.cat([now, others - now], dim=1).flatten(1, 2)
    expected = policy.idm_head(policy.idm_encoder(packed))
    torch.testing.assert_close(policy.idm_window_output(window), expected)
    moved = window.clone()
    moved[:, context, -1] += 1.0  # the state at t reaches the output
    assert not torch.allclose(policy.idm_window_output(moved), expected)


@pytest.mark.parametrize("fps, order", [(5, (TOP, SIDE, OBS_STATE)), (30, (TOP, OBS_STATE, SIDE))])
def test_the_camera_network_reads_its_frames_and_their_differences_as_they_are_packed(fps, order):
    """The linear-first IDM's camera network reads [x_t, x_j − x_t …] of its cameras' frames at ``camera_offsets``,
    cut per camera as it takes the differences, from views of the window where it can (frames t, t+1, t+2 at 5
    fps; cameras side by side) and gathered where it cannot (t, t+1, t+11 at 30 fps; the state between the
    cameras in ``--policy.observation_keys``); with and without gradients (the image encoder's stem then reads
    another memory format)."""
    features = {TOP: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 8, 8)),
                SIDE: PolicyFeature(type=FeatureType.VISUAL, shape=(3, 8, 8)),
                OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(2,))}  # fmt: skip
    config = IUPEConfig(
        input_features=features, observation_keys=list(order), action_low=[-1.0] * 3, action_high=[1.0] * 3,
        device="cpu", supervised=True, joint_state_columns=[0, 1, 0], idm_joint_lags=[0, 0, 0], fps=fps,
        idm_source_kinds=["camera", "camera", "position"],
    )  # fmt: skip
    torch.manual_seed(0)
    policy = IUPEPolicy(config).eval()
    torch.nn.init.normal_(policy.idm_camera.out.weight)  # zero at the start of training: it would hide its input
    for module in policy.modules():
        if hasattr(module, "gamma"):
            module.gamma.data.fill_(0.5)
    layout = policy.layout
    cameras = [i for i, key in enumerate(config.observation_keys) if key in config.camera_keys]
    assert (policy.camera_span is None) == (order[1] == OBS_STATE)
    frames = [config.idm_window.index(offset) for offset in config.camera_offsets]
    assert (frames == [0, 1, 2]) == (fps == 5)
    window = torch.rand(4, len(config.idm_window), layout.size, generator=torch.Generator().manual_seed(3))
    expected_frames = window[:, frames][:, :, layout.indices(cameras)]
    torch.testing.assert_close(policy.camera_frames(window), expected_frames, rtol=0, atol=0)
    start = expected_frames[:, :1]
    packed = torch.cat([start, expected_frames[:, 1:] - start], dim=1).flatten(1)
    expected = policy.idm_camera.out(policy.idm_camera.encoder(packed))
    torch.testing.assert_close(policy.idm_camera(policy.camera_frames(window)), expected)
    with torch.no_grad():
        torch.testing.assert_close(policy.idm_camera(policy.camera_frames(window)), expected)
    moved = window.clone()
    moved[:, frames[-1], layout.columns(cameras[-1])] += 0.5  # the last camera's latest frame reaches the output
    assert not torch.allclose(policy.idm_camera(policy.camera_frames(moved)), expected)


def test_a_supervised_linear_part_reads_the_vector_columns_without_a_camera_frame(tmp_path):
    """Windows of joined frames carry every camera value (4,096 of two 96×128 cameras were 4.8 GB at once): the
    linear part is fitted from the vector columns alone, read without joining a frame, and fits as from the whole
    windows."""
    from lerobot_iupe.data.readers import ExpertFrames
    from lerobot_iupe.policy.joint_fit import labelled_rows
    from lerobot_iupe.policy.linear_prior import LinearPrior, expert_features

    root = tmp_path / "three-views"
    write_three_views(root, episodes=3, seed=4, with_actions=True)
    dataset = LeRobotDataset(f"local/{root.name}", root=root)
    expert = ExpertFrames(dataset, [TOP, SIDE, OBS_STATE], True, torch.device("cpu"))
    offsets, vector_columns = [-1, 0, 1, 2], [2 * SIZE * SIZE * 3, 2 * SIZE * SIZE * 3 + 1]
    rows = labelled_rows(expert.episodes)
    joined = expert.windows(rows, offsets)
    np.testing.assert_array_equal(expert.column_windows(rows, offsets, vector_columns), joined[:, :, vector_columns])
    reversed_columns = vector_columns[::-1]  # any order of columns, as asked
    np.testing.assert_array_equal(
        expert.column_windows(rows, offsets, reversed_columns), joined[:, :, reversed_columns]
    )
    torch.testing.assert_close(expert.vector_windows(OBS_STATE, rows, offsets), joined[:, :, vector_columns])
    with pytest.raises(ValueError, match="camera"):
        expert.column_windows(rows, offsets, [0])

    joined_reads, windows = [], expert.windows
    expert.windows = lambda *args: joined_reads.append(args) or windows(*args)  # the real reader, counted
    prior = LinearPrior(len(offsets), vector_columns, 3)
    prior.fit(*expert_features(prior, expert, offsets), np.ones(3, dtype=bool))
    assert joined_reads == [] and bool(prior.fitted)
    whole = LinearPrior(len(offsets), vector_columns, 3)
    whole.fit(whole.features(joined.numpy()), expert.actions[rows].numpy(), np.ones(3, dtype=bool))
    torch.testing.assert_close(prior.weight, whole.weight)
    torch.testing.assert_close(prior.bias, whole.bias)


def test_a_camera_networks_frames_are_read_alone_as_the_whole_join_packs_them(tmp_path):
    """``part_windows`` packs some keys' values as the whole join does, without the others (the camera dimension's
    frames: reading every key and gathering the cameras' columns copied each camera value twice)."""
    from lerobot_iupe.data.readers import ExpertFrames
    from lerobot_iupe.policy.joint_fit import labelled_rows

    root = tmp_path / "three-views"
    write_three_views(root, episodes=2, seed=5, with_actions=True)
    dataset = LeRobotDataset(f"local/{root.name}", root=root)
    expert = ExpertFrames(dataset, [TOP, SIDE, OBS_STATE], True, torch.device("cpu"))
    rows, offsets = labelled_rows(expert.episodes), [0, 1, 5]
    joined = expert.windows(rows, offsets)
    layout = expert.states.layout
    for parts in ([0], [1], [0, 1], [1, 2], [0, 1, 2]):
        read = expert.part_windows(rows, offsets, parts)
        assert read.dtype == torch.float32 and read.shape == (len(rows), len(offsets), len(layout.indices(parts)))
        torch.testing.assert_close(read, joined[:, :, layout.indices(parts)], rtol=0, atol=0)


def test_cameras_and_state_join_to_the_same_floats_from_tensors_and_from_arrays():
    """The frames the IDM reads are packed from tensors (decoded frames, the frame cache) or numpy arrays (envs):
    uint8 pixels become x / 255 in float32, the same bits either way, and vectors are copied as they are."""
    from lerobot_iupe.data.observation import ObservationLayout

    layout = ObservationLayout(((3, 4, 5), (2,), (1, 4, 5)))
    rng = np.random.default_rng(0)
    parts = [rng.integers(0, 256, (7, 3, 4, 5), dtype=np.uint8), rng.normal(size=(7, 2)).astype(np.float32),
             rng.integers(0, 256, (7, 1, 4, 5), dtype=np.uint8)]  # fmt: skip
    from_arrays = layout.join(parts)
    from_tensors = layout.join([torch.from_numpy(part) for part in parts])
    assert from_tensors.dtype == torch.float32 and from_tensors.shape == (7, 3 * 20 + 2 + 20)
    np.testing.assert_array_equal(from_tensors.numpy(), from_arrays)
    np.testing.assert_array_equal(from_arrays[:, :60], parts[0].reshape(7, -1).astype(np.float32) / 255.0)
    np.testing.assert_array_equal(from_arrays[:, 60:62], parts[1])
