"""The VPT workflow on datasets written by LeRobot's own writer (no package metadata, no env): an IDM trained with
`lerobot-train --policy.supervised=true` on labelled episodes relabels state-only ones — continuous and discrete
actions, several observation keys, several cameras, a non-causal window, two processes — and the result passes
`lerobot-doctor` and trains LeRobot's ACT."""

import hashlib
import json
import shutil

import numpy as np
import pytest
import torch
from conftest import BIN, CHECKPOINT, once, run_cli, run_in_process
from lerobot.datasets import LeRobotDataset
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE
from safetensors.torch import load_file

from lerobot_iupe.data.readers import column_array, label_spans, span_windows, window_indices
from lerobot_iupe.hub import build_card
from lerobot_iupe.policy import IUPEConfig
from lerobot_iupe.policy.algorithm import r_squared

CAMERAS = ("observation.images.top", "observation.images.side")
ACTION_NAMES = ["force_x", "force_y"]


def write_point_mass(
    root, episodes: int, seed: int, with_actions: bool, discrete: bool = False, cameras: bool = False, fps: int = 10
) -> np.ndarray:
    """A point mass pushed towards a goal, written frame by frame with LeRobot's own writer: observation.state
    (position, velocity), observation.environment_state (goal), optionally two 64×64 cameras (video) and the
    action (float32 force, or int64 push left/none/right). Returns every frame's true action."""
    rng = np.random.default_rng(seed)
    features = {
        OBS_STATE: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "vx", "vy"]},
        OBS_ENV_STATE: {"dtype": "float32", "shape": (2,), "names": ["goal_x", "goal_y"]},
    }
    if cameras:
        for key in CAMERAS:
            features[key] = {"dtype": "video", "shape": (64, 64, 3), "names": ["height", "width", "channels"]}
    if with_actions:
        features[ACTION] = (
            {"dtype": "int64", "shape": (1,), "names": ["push"]}
            if discrete
            else {"dtype": "float32", "shape": (2,), "names": ACTION_NAMES}
        )
    dataset = LeRobotDataset.create(f"local/{root.name}", fps, features, root=root, use_videos=cameras)
    actions = []
    for _ in range(episodes):
        position, velocity = rng.uniform(-1, 1, 2), np.zeros(2)
        goal = rng.uniform(-1, 1, 2)
        for _ in range(int(rng.integers(20, 30))):
            if discrete:
                action = int(np.clip(np.sign(goal[0] - position[0]) + 1 + rng.integers(-1, 2), 0, 2))
                force = np.array([action - 1.0, 0.0])
            else:
                force = np.clip(goal - position - velocity + rng.normal(0, 0.3, 2), -1, 1)
                action = force.astype(np.float32)
            frame = {
                OBS_STATE: np.r_[position, velocity].astype(np.float32),
                OBS_ENV_STATE: goal.astype(np.float32),
                "task": "reach the goal",
            }
            if cameras:
                pixel = np.clip(((position + 2) / 4 * 64).astype(int), 0, 63)
                for i, key in enumerate(CAMERAS):
                    image = np.zeros((64, 64, 3), dtype=np.uint8)
                    image[pixel[i], pixel[1 - i], :] = 255
                    frame[key] = image
            if with_actions:
                frame[ACTION] = np.array([action], dtype=np.int64) if discrete else action
            dataset.add_frame(frame)
            actions.append(action)
            velocity = 0.8 * velocity + 0.2 * force
            position = position + 0.1 * velocity
        dataset.save_episode()
    dataset.finalize()
    return np.asarray(actions)


def train_idm(dataset, out, *flags: str, steps: int = 300):
    run_in_process(
        "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{dataset.name}",
        f"--dataset.root={dataset}", "--dataset.video_backend=pyav", f"--output_dir={out}", "--num_workers=0",
        "--policy.device=cpu", "--wandb.enable=false", f"--steps={steps}", f"--save_freq={steps}", "--batch_size=64",
        *flags, check=True
    )  # fmt: skip
    return out / CHECKPOINT


def relabel(checkpoint, dataset, *flags: str, check: bool = True, launcher: tuple[str, ...] = ()):
    args = [
        f"--policy.path={checkpoint}", f"--dataset.repo_id=local/{dataset.name}", f"--dataset.root={dataset}",
        "--dataset.video_backend=pyav", *flags,
    ]  # fmt: skip
    if launcher:
        return run_cli(*launcher, str(BIN / "lerobot-iupe-relabel"), *args, check=check)
    result = run_in_process("lerobot-iupe-relabel", *args)
    assert result.returncode == 0 or not check, result.stderr[-3000:]
    return result


def with_successor(dataset) -> np.ndarray:
    """Per frame, whether it has a successor in its episode (the last frame repeats the label before it)."""
    episodes = column_array(dataset.hf_dataset, "episode_index")
    return np.append(episodes[:-1] == episodes[1:], False)


def inner(actions: np.ndarray, dataset) -> np.ndarray:
    """The frames with a successor."""
    return actions[with_successor(dataset)]


@pytest.fixture(scope="session")
def work(shared_dir):
    path = shared_dir / "any"
    path.mkdir(exist_ok=True)
    return path


@pytest.fixture(scope="session")
def continuous_idm(work):
    """An IDM with a window of k = 1, trained on 12 labelled episodes of a LeRobot-written dataset (built once for
    every worker)."""
    labelled = work / "labelled"

    def make():
        shutil.rmtree(labelled, ignore_errors=True)
        shutil.rmtree(work / "idm", ignore_errors=True)
        write_point_mass(labelled, episodes=12, seed=0, with_actions=True)
        train_idm(labelled, work / "idm", "--policy.idm_context=1")

    return once(work / "idm", make, CHECKPOINT) / CHECKPOINT


def test_window_indices_clamp_into_the_episode():
    t = np.array([10, 11, 14])
    index = window_indices(t, [-1, 0, 1, 2], first=np.full(3, 10), last=np.full(3, 14))
    np.testing.assert_array_equal(index, [[10, 10, 11, 12], [10, 11, 12, 13], [13, 14, 14, 14]])


@pytest.mark.parametrize("offsets", [[-1, 0, 1, 2], [0, 1], [-3, -2, -1, 0, 1, 2, 3, 4]])
@pytest.mark.parametrize("batch", [2, 3, 32])
def test_span_windows_are_the_windows_of_clamped_indices_copying_only_passes_at_an_edge(offsets, batch):
    bounds = [(0, 3), (3, 40)]
    frames = torch.arange(40 * 6, dtype=torch.float32).reshape(40, 2, 3)  # every value names its frame
    for span in label_spans(bounds, batch_size=7, offsets=offsets):
        t = np.arange(span.start, span.stop)
        index = window_indices(t, offsets, np.full(len(t), span.first), np.full(len(t), span.last))
        part = frames[span.lo : span.hi + 1]
        passes = span_windows(part, span, offsets, batch)
        assert [len(p) for p in passes] == [len(c) for c in torch.arange(len(t)).split(batch)]
        for windows, rows in zip(passes, torch.as_tensor(index - span.lo).split(batch), strict=True):
            assert torch.equal(windows, part[rows])
            if bool((rows[1:, 0] - rows[:-1, 0] == 1).all()) and bool((rows[:, 1:] - rows[:, :-1] == 1).all()):
                assert windows.data_ptr() == part[int(rows[0, 0])].data_ptr()  # a view of the frames
    with pytest.raises(ValueError, match="consecutive offsets"):
        span_windows(frames, label_spans(bounds, 7, [0, 2])[0], [0, 2], 32)


def test_label_spans_cover_every_frame_with_a_successor_once_and_load_the_window():
    bounds = [(0, 7), (7, 8), (8, 20)]  # a one-frame episode has nothing to label
    spans = label_spans(bounds, batch_size=5, offsets=[-1, 0, 1, 2])
    labelled = [t for s in spans for t in range(s.start, s.stop)]
    assert labelled == [*range(0, 6), *range(8, 19)]
    for s in spans:
        first, end = bounds[s.episode]
        assert s.lo == max(first, s.start - 1) and s.hi == min(end - 1, s.stop - 1 + 2)
        assert s.stop - s.start <= 5
    assert [s.episode for s in label_spans(bounds, 5, [0, 1], episodes=[2])] == [2, 2, 2]


def test_a_supervised_idm_relabels_lerobot_written_continuous_data(continuous_idm, work):
    config = json.loads((continuous_idm / "config.json").read_text())
    assert config["env_settings"] is None and config["fps"] == 10 and config["idm_context"] == 1
    assert config["action_names"] == ACTION_NAMES and config["observation_keys"] == [OBS_STATE, OBS_ENV_STATE]
    held_out = work / "held-out"
    true = write_point_mass(held_out, episodes=6, seed=1, with_actions=False)
    assert not (held_out / "meta" / "iupe.json").exists()  # LeRobot's files only
    result = relabel(continuous_idm, held_out)
    assert "R²" not in result.stdout  # nothing to compare with
    dataset = LeRobotDataset(f"local/{held_out.name}", root=held_out)
    feature = dataset.meta.features[ACTION]
    assert feature["dtype"] == "float32" and tuple(feature["shape"]) == (2,) and feature["names"] == ACTION_NAMES
    labels = column_array(dataset.hf_dataset, ACTION)
    assert r_squared(inner(labels, dataset), inner(true, dataset)) > 0.9
    stats = dataset.meta.stats[ACTION]
    assert set(stats) == set(dataset.meta.stats[OBS_STATE])  # the same statistics LeRobot computes for a feature
    np.testing.assert_allclose(stats["mean"], labels.mean(axis=0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(stats["max"], labels.max(axis=0), rtol=1e-6)

    card = str(build_card(held_out, "me/held-out"))
    assert str(continuous_idm) in card and "float32 (2,): force_x, force_y" in card

    after = doctor(held_out)
    assert after["overall_severity"] != "FAIL", json.dumps(after["checks"])[-3000:]
    assert not [c["name"] for c in after["checks"] if c["severity"] == "FAIL"]


def doctor(root) -> dict:
    """The third-party checker's verdict on a dataset (lerobot-doctor from PyPI)."""
    result = run_cli("lerobot-doctor", "check", str(root), "--json", check=False)
    return json.loads(result.stdout[result.stdout.index("{") :])


def test_lerobot_doctor_fails_the_state_only_dataset_it_passes_once_relabelled(work):
    state_only = work / "state-only"
    write_point_mass(state_only, episodes=2, seed=12, with_actions=False)
    assert doctor(state_only)["overall_severity"] == "FAIL"  # "no action features": the checker can fail


# Each policy small enough for a CPU test; Diffusion reads the point mass's environment_state (it needs an image or
# that) and normalises actions by their range, ACT by their mean and std.
CHUNKED_POLICIES = {
    "act": ["--policy.type=act", "--policy.chunk_size=5", "--policy.n_action_steps=5", "--policy.dim_model=32",
            "--policy.n_heads=2", "--policy.dim_feedforward=64"],
    "diffusion": ["--policy.type=diffusion", "--policy.down_dims=[16,32]", "--policy.horizon=8",
                  "--policy.n_action_steps=4", "--policy.diffusion_step_embed_dim=16"],
}  # fmt: skip


@pytest.mark.parametrize("policy", list(CHUNKED_POLICIES))
def test_lerobots_chunked_policies_train_on_the_relabelled_labels(continuous_idm, work, policy):
    dataset = work / f"for-{policy}"
    write_point_mass(dataset, episodes=3, seed=2, with_actions=False)
    relabel(continuous_idm, dataset)
    out = work / policy
    run_in_process(
        "lerobot-train", *CHUNKED_POLICIES[policy], f"--dataset.repo_id=local/{dataset.name}",
        f"--dataset.root={dataset}", f"--output_dir={out}", "--steps=3", "--batch_size=4", "--num_workers=0",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false", "--save_freq=3", check=True
    )  # fmt: skip
    # the policy predicts our 2-D labels and normalises them by stats that are those of the written labels
    config = json.loads((out / CHECKPOINT / "config.json").read_text())
    assert config["type"] == policy and config["output_features"]["action"]["shape"] == [2]
    labels = column_array(LeRobotDataset(f"local/{dataset.name}", root=dataset).hf_dataset, "action")
    stats = load_file(out / CHECKPOINT / "policy_postprocessor_step_0_unnormalizer_processor.safetensors")
    if policy == "act":
        np.testing.assert_allclose(stats["action.mean"].numpy(), labels.mean(0), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(stats["action.std"].numpy(), labels.std(0), rtol=1e-3, atol=1e-5)
    else:
        np.testing.assert_allclose(stats["action.min"].numpy(), labels.min(0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(stats["action.max"].numpy(), labels.max(0), rtol=1e-5, atol=1e-6)


def test_the_chunks_lerobot_reads_from_a_relabelled_dataset_follow_the_true_actions_step_by_step(continuous_idm, work):
    """What a chunked policy trains on: at each frame t LeRobot's dataset reads the actions t … t+4 (its
    delta_timestamps from ACT's own config). On a relabelled dataset position i of that chunk is the label of the
    transition t+i → t+i+1, so it follows the true action of step t+i, not its neighbour's."""
    dataset, offsets, fps = work / "chunks", ACTConfig(chunk_size=5, n_action_steps=5).action_delta_indices, 10
    true = write_point_mass(dataset, episodes=4, seed=7, with_actions=False, fps=fps)
    relabel(continuous_idm, dataset)
    chunk = {ACTION: [i / fps for i in offsets]}
    frames = LeRobotDataset(f"local/{dataset.name}", root=dataset, delta_timestamps=chunk)
    # steps whose label and successor's label are both read off a transition (an episode's last frame has none)
    labelled = with_successor(frames)
    read, aligned, one_late = [], [], []
    for t in range(len(frames)):
        item = frames[t]
        for i, offset in enumerate(offsets):
            step = t + offset
            if item["action_is_pad"][i] or not labelled[step] or not labelled[step + 1]:
                continue
            read.append(item[ACTION][i].numpy())
            aligned.append(true[step])
            one_late.append(true[step + 1])
    read, aligned, one_late = np.array(read), np.array(aligned), np.array(one_late)
    assert len(read) > 200
    assert r_squared(read, aligned) > 0.9
    assert r_squared(read, one_late) < r_squared(read, aligned) - 0.2


def test_two_processes_write_the_same_bytes_as_one(continuous_idm, work):
    one, two = work / "one-process", work / "two-processes"
    write_point_mass(one, episodes=5, seed=3, with_actions=False)
    shutil.copytree(one, two)
    relabel(continuous_idm, one, "--batch_size=7", "--mode=sample", "--seed=4")
    result = relabel(
        continuous_idm, two, "--batch_size=7", "--mode=sample", "--seed=4",
        launcher=("torchrun", "--nproc_per_node=2", "--standalone"),
    )  # fmt: skip
    assert "on 2 processes" in result.stdout, result.stdout + result.stderr[-3000:]
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file() and p.name != "iupe.json")
    assert files == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file() and p.name != "iupe.json")
    labels = [column_array(LeRobotDataset("local/x", root=root).hf_dataset, ACTION) for root in (one, two)]
    np.testing.assert_array_equal(labels[0], labels[1])
    for name in files:
        assert (one / name).read_bytes() == (two / name).read_bytes(), name


def test_a_discrete_supervised_idm_from_lerobot_written_data(work):
    labelled, held_out = work / "discrete-labelled", work / "discrete-held-out"
    write_point_mass(labelled, episodes=12, seed=5, with_actions=True, discrete=True)
    checkpoint = train_idm(labelled, work / "discrete-idm", steps=200)
    config = json.loads((checkpoint / "config.json").read_text())
    assert config["n_actions"] == 3 and config["idm_context"] == 1  # the supervised default
    true = write_point_mass(held_out, episodes=6, seed=6, with_actions=False, discrete=True)
    relabel(checkpoint, held_out)
    dataset = LeRobotDataset(f"local/{held_out.name}", root=held_out)
    assert dataset.meta.features[ACTION]["dtype"] == "int64"
    labels = column_array(dataset.hf_dataset, ACTION).reshape(-1)
    assert (inner(labels, dataset) == inner(true, dataset)).mean() >= 0.95


def test_two_cameras_and_the_state_are_read_videos_untouched_and_a_mismatch_is_named(work):
    labelled, held_out = work / "cameras-labelled", work / "cameras-held-out"
    write_point_mass(labelled, episodes=3, seed=7, with_actions=True, cameras=True)
    checkpoint = train_idm(labelled, work / "cameras-idm", steps=4)
    keys = json.loads((checkpoint / "config.json").read_text())["observation_keys"]
    assert keys == [*CAMERAS, OBS_STATE, OBS_ENV_STATE]  # the whole observation, cameras and vectors fused
    write_point_mass(held_out, episodes=2, seed=8, with_actions=False, cameras=True)
    videos = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in held_out.rglob("*.mp4")}
    relabel(checkpoint, held_out)
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in held_out.rglob("*.mp4")} == videos
    assert len(videos) == 2  # labelling reads the videos and writes none
    dataset = LeRobotDataset(f"local/{held_out.name}", root=held_out, video_backend="pyav")
    assert dataset.meta.features[ACTION]["dtype"] == "float32" and len(dataset.hf_dataset) == dataset.meta.total_frames

    no_cameras = work / "no-cameras"
    write_point_mass(no_cameras, episodes=1, seed=9, with_actions=False)
    files = sorted(p.relative_to(no_cameras) for p in no_cameras.rglob("*"))
    result = relabel(checkpoint, no_cameras, check=False)
    assert result.returncode == 2 and "observation.images.top" in result.stderr and "--policy.path" in result.stderr
    assert sorted(p.relative_to(no_cameras) for p in no_cameras.rglob("*")) == files


def test_incompatible_fps_and_action_names_are_refused_naming_both_sides(continuous_idm, work):
    fast = work / "fast"
    write_point_mass(fast, episodes=1, seed=10, with_actions=False, fps=20)
    result = relabel(continuous_idm, fast, check=False)
    assert result.returncode == 2 and "fps" in result.stderr and "20" in result.stderr and "10" in result.stderr

    renamed = work / "renamed"
    write_point_mass(renamed, episodes=1, seed=11, with_actions=True)
    info_path = renamed / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"][ACTION]["names"] = ["joint_1", "joint_2"]
    info_path.write_text(json.dumps(info, indent=4))
    before = {p: p.read_bytes() for p in renamed.rglob("*") if p.is_file()}
    result = relabel(continuous_idm, renamed, "--overwrite=true", check=False)
    assert result.returncode == 2 and "joint_1" in result.stderr and "force_x" in result.stderr
    assert before == {p: p.read_bytes() for p in renamed.rglob("*") if p.is_file()}

    discrete = work / "discrete-actions"
    write_point_mass(discrete, episodes=1, seed=13, with_actions=True, discrete=True)
    before = {p: p.read_bytes() for p in discrete.rglob("*") if p.is_file()}
    result = relabel(continuous_idm, discrete, "--overwrite=true", check=False)
    assert result.returncode == 2 and "int64" in result.stderr and "float32" in result.stderr
    assert before == {p: p.read_bytes() for p in discrete.rglob("*") if p.is_file()}


def test_a_negative_window_is_refused_naming_the_flag():
    with pytest.raises(ValueError, match="--policy.idm_context"):
        IUPEConfig(idm_context=-1, supervised=True)
