"""Every action dimension from its best source (policy/joint_idm.py's source kinds), end to end on the generator's
hand-guided arm (``VELOCITY_ARM``: measured joint velocities ``joint_i_vel`` over positions ``joint_i`` at 10 fps with
jittered real time steps, and a keyboard gripper that only the wrist camera shows): lerobot-train with default flags
on two labelled episodes, then lerobot-iupe-relabel --dry_run=true on held-out ones."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, once, run_in_process, train_once
from lerobot.datasets import LeRobotDataset
from test_arm_idm import reference_table

from lerobot_iupe.data.arm_writer import write_arm_recording
from lerobot_iupe.data.hand_guided_arm import VELOCITY_ARM
from lerobot_iupe.policy import IUPEPolicy

VELOCITIES = [name for name in VELOCITY_ARM.action_names if name.endswith("_vel")]
IDLE = "joint_4"


def velocity_pair(data_dir, name: str, cameras: bool) -> tuple:
    """Two labelled episodes (``IDLE`` resting in them) and three held-out ones where every joint moves, with actions;
    cameras at 48×64."""
    roots = []
    for part, episodes, seed, idle in (("", 2, 0, (IDLE,)), ("-held-out", 3, 100, ())):
        root = data_dir / f"{name}{part}"
        write = lambda root=root, n=episodes, s=seed, idle=idle: write_arm_recording(  # noqa: E731
            root, n, 150, height=48, width=64, fps=10, seed=s, repo_id=f"local/{root.name}", cameras=cameras,
            body=VELOCITY_ARM, idle=idle,
        )  # fmt: skip
        roots.append(once(root, write, "meta/info.json"))
    return tuple(roots)


def default_run(shared_dir, labelled, steps: int) -> tuple:
    out = shared_dir / "runs" / labelled.name
    run = train_once(
        out, "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{labelled.name}",
        f"--dataset.root={labelled}", "--batch_size=32", f"--steps={steps}", f"--save_freq={steps}",
        "--num_workers=0", "--policy.device=cpu", "--policy.push_to_hub=false", "--wandb.enable=false",
        f"--output_dir={out}",
    )  # fmt: skip
    return run / CHECKPOINT, json.loads((run / CHECKPOINT / "config.json").read_text())


def dry_run(checkpoint, held_out) -> str:
    result = run_in_process(
        "lerobot-iupe-relabel", f"--policy.path={checkpoint}", "--dataset.repo_id=local/x",
        f"--dataset.root={held_out}", "--dry_run=true", "--dataset.video_backend=pyav", check=True,
    )  # fmt: skip
    return result.stdout


def difference_copies(stdout: str) -> dict[str, float]:
    """{dimension: R² of its best difference copy} from the dry run's table (dimensions that have one)."""
    rows = re.findall(r"^  (\S+)\s.*?\s(-?[\d.]+) \(d=\s*-?\d+\)", stdout, re.MULTILINE)
    return {name: float(value) for name, value in rows}


def test_velocities_are_labelled_from_their_columns_differences_no_worse_than_the_difference_copy(data_dir, shared_dir):
    labelled, held_out = velocity_pair(data_dir, "velocity-arm", cameras=False)
    checkpoint, config = default_run(shared_dir, labelled, 100)
    assert config["idm_source_kinds"][:6] == ["difference"] * 6
    assert config["joint_state_columns"][:6] == list(range(6))  # joint_i_vel reads joint_i: the stems match
    out = dry_run(checkpoint, held_out)
    table, differences = reference_table(out), difference_copies(out)
    assert set(VELOCITIES) <= set(table) and set(VELOCITIES) <= set(differences), out
    for joint in VELOCITIES:
        idm = table[joint][0]
        assert idm >= differences[joint] - 0.005, f"{joint}: IDM {idm} vs difference copy {differences[joint]}\n{out}"
    # The joint idle in the labelled episodes moves in the held-out ones: there it borrows the other velocities'
    # filter (no pose term), where a fit over every column's window extrapolates.
    idm, _, ridge, _ = table[f"{IDLE}_vel"]
    assert differences[f"{IDLE}_vel"] > 0.5 and idm > ridge, out
    assert json.loads((checkpoint / "config.json").read_text())["idm_source_kinds"][4] == "difference"


def test_a_keyboard_gripper_that_only_the_camera_shows_is_read_off_the_camera_and_only_it(data_dir, shared_dir):
    labelled, held_out = velocity_pair(data_dir, "velocity-arm-cameras", cameras=True)
    checkpoint, config = default_run(shared_dir, labelled, 60)
    assert config["idm_source_kinds"] == ["difference"] * 6 + ["camera"]
    policy = IUPEPolicy.from_pretrained(checkpoint).eval()
    assert set(policy.labelling_keys) == {"observation.state", *policy.config.camera_keys}
    assert policy.config.camera_offsets == [0, 1, 5]  # t, t + 1 and t + 0.5 s at 10 fps
    # The velocities do not depend on the cameras; the gripper does.
    generator = torch.Generator().manual_seed(0)
    state = torch.randn(4, len(policy.config.idm_window), 6, generator=generator)
    offsets = len(policy.config.camera_offsets)
    frames = [torch.rand(4, offsets, policy.camera_columns.numel(), generator=generator) for _ in range(2)]
    with torch.no_grad():
        outputs = [policy.joint_idm_output(state, gated=False, camera=f)[:, :7] for f in frames]
    torch.testing.assert_close(outputs[0][:, :6], outputs[1][:, :6])
    assert not torch.allclose(outputs[0][:, 6], outputs[1][:, 6])
    with pytest.raises(ValueError, match="read off the cameras"):
        policy.joint_idm_output(state)
    out = dry_run(checkpoint, held_out)  # the relabelling path decodes the cameras and labels every dimension
    rows = {line.split()[0]: line for line in out.splitlines() if line.startswith("  ")}
    assert "camera" in rows["gripper"] and all("difference" in rows[joint] for joint in VELOCITIES), out
    assert "(ridge on thumbnails)" in rows["gripper"] and not any("thumbnails" in rows[j] for j in VELOCITIES), out
    idm, _, thumbnail_ridge, _ = reference_table(out)["gripper"]
    assert np.isfinite(idm) and np.isfinite(thumbnail_ridge)


def write_pushed_hand(root, episodes: int, seed: int) -> None:
    """A hand commanded in deltas (``dx``, ``dy``) that pushes an object: it moves by 0.01·a_t less what the object
    resists (``observation.environment_state``, a slowly varying force), as Meta-World's hand does on push. The
    hand's own motion tells about three quarters of the command; the rest shows only in the environment state."""
    rng = np.random.default_rng(seed)
    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["hand.x", "hand.y"]},
        "observation.environment_state": {"dtype": "float32", "shape": (2,), "names": ["resist.x", "resist.y"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "dy"]},
    }
    dataset = LeRobotDataset.create(f"local/{root.name}", 10, features, root=root, use_videos=False)
    for _ in range(episodes):
        hand, command, resist = np.zeros(2), np.zeros(2), np.zeros(2)
        for _ in range(80):
            command = np.clip(0.8 * command + rng.normal(0, 0.4, 2), -1, 1)
            resist = 0.8 * resist + rng.normal(0, 0.25, 2)
            dataset.add_frame({
                "observation.state": hand.astype(np.float32),
                "observation.environment_state": resist.astype(np.float32),
                "action": command.astype(np.float32), "task": "push",
            })  # fmt: skip
            hand = hand + 0.01 * (command - 0.6 * resist)
        dataset.save_episode()
    dataset.finalize()


def test_a_delta_is_read_off_its_columns_difference_and_what_the_environment_state_shows(data_dir, shared_dir):
    labelled, held_out = data_dir / "pushed-hand", data_dir / "pushed-hand-held-out"
    once(labelled, lambda: write_pushed_hand(labelled, 6, seed=0), "meta/info.json")
    once(held_out, lambda: write_pushed_hand(held_out, 3, seed=100), "meta/info.json")
    checkpoint, config = default_run(shared_dir, labelled, 100)
    assert config["idm_source_kinds"] == ["difference", "difference"]
    assert config["idm_observation_keys"] == ["observation.state", "observation.environment_state"]
    table = reference_table(dry_run(checkpoint, held_out))
    # Off the hand's own difference alone a delta scores about 0.75 here; with the resisting force 1.
    assert all(idm > 0.99 for idm, *_ in table.values()), table
