"""lerobot-iupe-relabel on real datasets with real checkpoints: labels, metadata, safety, hub."""

import errno
import hashlib
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import BIN, CHECKPOINT, collect, run_cli, run_in_process, still_alive_after, train_args
from hub_server import LocalHub
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.dataset_tools import remove_feature
from test_hub import hub_env

from lerobot_iupe.benchmark import evaluate_checkpoint
from lerobot_iupe.collect import dataset_features
from lerobot_iupe.data.readers import column_array, stored_frames
from lerobot_iupe.data.storage import read_iupe_meta, write_iupe_meta
from lerobot_iupe.envs.configs import CartPoleEnvConfig
from lerobot_iupe.relabel import CheckpointRef, RelabelConfig, RelabelDataset, relabel
from lerobot_iupe.relabel import run as relabel_run


def tree_digest(root) -> dict:
    files = (p for p in root.rglob("*") if p.is_file())
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


def hidden_siblings(root) -> list:
    return sorted(p.name for p in root.parent.iterdir() if p.name.startswith(f".{root.name}."))


def labelled_and_stripped(data_dir, name: str, *collect_args: str):
    """An expert dataset collected with its true actions, and a copy with the actions removed by LeRobot."""
    labelled = collect(data_dir, f"{name}-true", *collect_args, "--agent=expert", "--keep_actions=true")
    stripped = data_dir / f"{name}-{os.getpid()}-{time.monotonic_ns()}"
    source = LeRobotDataset(f"local/{name}-true", root=labelled, video_backend="pyav")
    remove_feature(source, "action", output_dir=stripped, repo_id=f"local/{stripped.name}")
    write_iupe_meta(stripped, {**read_iupe_meta(labelled), "has_actions": False})  # LeRobot copies only its files
    return labelled, stripped


def relabel_args(checkpoint, root, *extra: str) -> list[str]:
    return [
        f"--policy.path={checkpoint}", "--policy.device=cpu", f"--dataset.repo_id=local/{root.name}",
        f"--dataset.root={root}", *extra,
    ]  # fmt: skip


def true_actions(root) -> tuple[np.ndarray, np.ndarray]:
    table = LeRobotDataset("local/x", root=root, video_backend="pyav").hf_dataset
    episodes = column_array(table, "episode_index")
    has_next = np.append(episodes[:-1] == episodes[1:], False)
    return column_array(table, "action").reshape(-1), has_next


def test_relabelled_state_dataset_matches_the_true_actions(cartpole_run, data_dir):
    checkpoint = cartpole_run / CHECKPOINT
    labelled, stripped = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    result = run_in_process("lerobot-iupe-relabel", *relabel_args(checkpoint, stripped), check=True)
    assert "frames/s" in result.stdout
    dataset = LeRobotDataset(f"local/{stripped.name}", root=stripped)
    feature = dataset.meta.features["action"]
    assert feature["dtype"] == "int64" and tuple(feature["shape"]) == (1,)
    assert feature["info"]["labelled_by"] == str(checkpoint) and len(feature["info"]["checkpoint_sha256"]) == 16
    info = json.loads((stripped / "meta" / "info.json").read_text())
    assert info["features"]["action"]["info"]["mode"] == "argmax"
    assert set(dataset.meta.stats["action"]) >= {"mean", "std", "min", "max"}
    assert dataset[0]["action"].shape == ()
    new, has_next = true_actions(stripped)
    old, _ = true_actions(labelled)
    assert (new[has_next] == old[has_next]).mean() >= 0.95  # IDM of a normal run labels like the expert
    last = np.flatnonzero(~has_next)
    assert np.array_equal(new[last], new[last - 1])  # the documented last-frame rule
    meta = json.loads((stripped / "meta" / "iupe.json").read_text())
    assert meta["relabelled_by"]["checkpoint"] == str(checkpoint) and meta["has_actions"]
    assert hidden_siblings(stripped) == []


def test_bc_on_a_relabelled_cartpole_dataset_reaches_475(cartpole_run, cartpole_random, data_dir, tmp_path):
    _, stripped = labelled_and_stripped(data_dir, "cartpole-bc", "--env.type=cartpole", "--episodes=10")
    run_in_process("lerobot-iupe-relabel", *relabel_args(cartpole_run / CHECKPOINT, stripped), check=True)
    out = tmp_path / "bc"
    run_in_process(
        "lerobot-train",
        *train_args(stripped, cartpole_random, out, "--steps=300", "--batch_size=128", "--policy.supervised=true"),
        check=True,
    )
    result = evaluate_checkpoint(out / CHECKPOINT, CartPoleEnvConfig(), episodes=20)  # lerobot-eval's path, no videos
    assert result["avg_sum_reward"] >= 475


def test_existing_actions_are_refused_without_overwrite_and_compared_in_dry_run(cartpole_run, data_dir):
    labelled, _ = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    before = tree_digest(labelled)
    refused = run_in_process("lerobot-iupe-relabel", *relabel_args(cartpole_run / CHECKPOINT, labelled))
    assert refused.returncode == 2 and "--overwrite=true" in refused.stderr
    dry = run_in_process("lerobot-iupe-relabel", *relabel_args(cartpole_run / CHECKPOINT, labelled, "--dry_run=true"))
    assert "nothing written" in dry.stdout and "agreement with the dataset's existing actions" in dry.stdout
    assert tree_digest(labelled) == before


def test_overwrite_replaces_existing_actions(cartpole_run, data_dir, tmp_path):
    labelled, _ = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    copy = tmp_path / "copy"
    LeRobotDataset("local/x", root=labelled)  # the dataset loads before the copy is relabelled
    subprocess.run(["cp", "-r", str(labelled), str(copy)], check=True)
    result = run_in_process(
        "lerobot-iupe-relabel", *relabel_args(cartpole_run / CHECKPOINT, copy, "--overwrite=true"), check=True
    )
    assert "agreement" in result.stdout
    assert LeRobotDataset("local/copy", root=copy).meta.features["action"]["info"]["mode"] == "argmax"


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("image_dataset", "the checkpoint --policy.path reads 'observation.state'"),
        ("other_state_size", "has shape (6,) in the dataset"),
        ("not_a_checkpoint", "holds no config.json"),
        ("missing_checkpoint", "/no-such-run/pretrained_model does not exist"),
        ("empty_dataset", "holds no episodes"),
        ("bad_mode", "--mode=greedy"),
        ("bad_threads", "--num_threads must be at least 1"),
        ("bad_workers", "--num_workers must be 0 (no worker processes) or more, got -1"),
        ("bad_pull", "--pull_to_observation must be 0 (the IDM's own labels) or more, got -1"),
        ("pull_discrete", "--pull_to_observation applies to continuous actions"),
    ],
)
def test_mismatches_are_clear_errors_and_write_nothing(case, message, cartpole_run, maze_expert, data_dir, tmp_path):
    checkpoint, dataset, extra = cartpole_run / CHECKPOINT, data_dir / "cartpole-expert", []
    if case == "image_dataset":
        dataset = maze_expert
    elif case == "other_state_size":
        dataset = collect(tmp_path, "acrobot", "--env.type=acrobot", "--agent=expert", "--episodes=1")
    elif case == "not_a_checkpoint":
        checkpoint = tmp_path
    elif case == "missing_checkpoint":
        checkpoint = tmp_path / "no-such-run" / "pretrained_model"
    elif case == "empty_dataset":  # created and finalised with no episodes
        dataset = tmp_path / "empty"
        features = dataset_features(CartPoleEnvConfig(), with_actions=False)
        LeRobotDataset.create("local/empty", fps=50, features=features, root=dataset).finalize()
    elif case == "bad_mode":
        extra = ["--mode=greedy"]
    elif case == "bad_threads":
        extra = ["--num_threads=0"]
    elif case == "bad_workers":
        extra = ["--num_workers=-1"]
    elif case == "bad_pull":
        extra = ["--pull_to_observation=-1"]
    elif case == "pull_discrete":
        extra = ["--pull_to_observation=1"]
    before = tree_digest(dataset)
    result = run_in_process("lerobot-iupe-relabel", *relabel_args(checkpoint, dataset, *extra))
    assert result.returncode == 2 and one_error_line(result).count(message) == 1, result.stderr[-2000:]
    assert tree_digest(dataset) == before and hidden_siblings(dataset) == []


def one_error_line(result) -> str:
    """The command's error: one line, no traceback."""
    assert "Traceback" not in result.stderr, result.stderr[-3000:]
    return result.stderr.strip().splitlines()[-1]


@pytest.mark.skipif(subprocess.run(["unshare", "-rm", "true"]).returncode != 0, reason="no user namespaces")
def test_a_read_only_parent_folder_is_refused_before_any_labelling(cartpole_run, data_dir, tmp_path):
    # a real read-only mount (root ignores file modes): the dataset's folder is bind-mounted read-only
    _, stripped = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    folder = tmp_path / "read-only"
    folder.mkdir()
    root = folder / "demos"
    subprocess.run(["cp", "-r", str(stripped), str(root)], check=True)
    before = tree_digest(root)
    command = [str(BIN / "lerobot-iupe-relabel"), *relabel_args(cartpole_run / CHECKPOINT, root)]
    script = f'mount --bind -o ro "{folder}" "{folder}" && exec "$@"'
    result = subprocess.run(["unshare", "-rm", "sh", "-c", script, "sh", *command], capture_output=True, text=True)
    assert result.returncode == 2 and "Read-only file system" in one_error_line(result), result.stderr[-2000:]
    assert f"cannot write in its folder {folder}" in one_error_line(result)
    assert "relabel:" not in result.stderr  # no progress bar: refused before labelling
    assert tree_digest(root) == before and sorted(p.name for p in folder.iterdir()) == ["demos"]


@pytest.mark.parametrize(
    ("old", "new"),
    [
        ("--device=cpu", "--policy.device"),
        ("--video_backend=pyav", "--dataset.video_backend"),
        ("--push_to_hub=true", "--dataset.push_to_hub"),
    ],
)
def test_the_old_flag_names_point_to_lerobots(old, new, cartpole_run, cartpole_expert):
    result = run_in_process("lerobot-iupe-relabel", *relabel_args(cartpole_run / CHECKPOINT, cartpole_expert, old))
    assert result.returncode == 2 and f"is now {new}" in one_error_line(result)


def test_video_dataset_is_relabelled_in_streaming_batches(maze_run, data_dir):
    _, stripped = labelled_and_stripped(data_dir, "maze3-relabel", "--env.type=maze", "--env.size=3", "--episodes=3")
    videos_before = {k: v for k, v in tree_digest(stripped).items() if k.startswith("videos/")}
    args = relabel_args(maze_run / CHECKPOINT, stripped, "--dataset.video_backend=pyav", "--batch_size=4")
    dry_a = run_in_process(
        "lerobot-iupe-relabel", *args, "--mode=sample", "--seed=3", "--dry_run=true", check=True
    ).stdout
    dry_b = run_in_process(
        "lerobot-iupe-relabel", *args, "--mode=sample", "--seed=3", "--dry_run=true", check=True
    ).stdout
    shares = [[line for line in out.splitlines() if line.startswith("  actions")] for out in (dry_a, dry_b)]
    assert shares[0] and shares[0] == shares[1]  # same seed, same label statistics
    run_in_process("lerobot-iupe-relabel", *args, check=True)
    dataset = LeRobotDataset(f"local/{stripped.name}", root=stripped, video_backend="pyav")
    assert dataset.meta.features["action"]["dtype"] == "int64"
    frame = dataset[1]
    assert frame["observation.image"].shape == (3, 64, 64) and 0 <= int(frame["action"]) < 4
    assert {k: v for k, v in tree_digest(stripped).items() if k.startswith("videos/")} == videos_before


def test_png_frame_dataset_is_relabelled_and_keeps_its_frames(maze_run, data_dir):
    _, stripped = labelled_and_stripped(
        data_dir, "maze3-png-relabel", "--env.type=maze", "--env.size=3", "--episodes=2", "--video=false"
    )
    before = stored_frames(LeRobotDataset(f"local/{stripped.name}", root=stripped), "observation.image")
    run_in_process("lerobot-iupe-relabel", *relabel_args(maze_run / CHECKPOINT, stripped, "--batch_size=4"), check=True)
    dataset = LeRobotDataset(f"local/{stripped.name}", root=stripped)
    assert dataset.meta.features["observation.image"]["dtype"] == "image"
    assert np.array_equal(stored_frames(dataset, "observation.image"), before)
    assert 0 <= int(dataset[1]["action"]) < 4


def test_a_failure_while_writing_keeps_the_original(cartpole_run, data_dir, monkeypatch):
    _, stripped = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    before = tree_digest(stripped)

    def disk_full(staged, labels, feature):
        (staged / "data" / "filler.bin").write_bytes(b"0" * 1024)
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(relabel_run, "write_labels", disk_full)
    cfg = RelabelConfig(
        policy=CheckpointRef(str(cartpole_run / CHECKPOINT)),
        dataset=RelabelDataset(repo_id=f"local/{stripped.name}", root=str(stripped)),
    )
    with pytest.raises(OSError, match="No space left"):
        relabel(cfg)
    assert tree_digest(stripped) == before and hidden_siblings(stripped) == []


def test_kill_9_after_the_copy_is_written_loses_nothing(maze_run, maze_random, data_dir, tmp_path):
    """A real SIGKILL once the relabelled copy is complete, just before it is swapped in (every step of the swap
    itself is killed in test_swap.py)."""
    root = tmp_path / "maze-random"
    subprocess.run(["cp", "-r", str(maze_random), str(root)], check=True)
    before = tree_digest(root)
    args = relabel_args(maze_run / CHECKPOINT, root, "--overwrite=true", "--dataset.video_backend=pyav")
    code = (
        "import os, signal, sys; from lerobot_iupe.data import storage as dataset_utils;"
        "dataset_utils.exchange_paths = lambda *a: os.kill(os.getpid(), signal.SIGKILL);"
        "from lerobot_iupe.cli.relabel import main; sys.argv[1:] = sys.argv[2:]; main()"
    )
    process = subprocess.run([sys.executable, "-c", code, "relabel", *args], capture_output=True, text=True)
    assert process.returncode == -signal.SIGKILL, process.stderr[-3000:]
    staged = [name for name in hidden_siblings(root) if ".partial-" in name]
    assert len(staged) == 1
    assert "relabelled_by" in read_iupe_meta(root.parent / staged[0])  # the copy was complete
    assert tree_digest(root) == before
    LeRobotDataset("local/maze-random", root=root, video_backend="pyav")[0]
    run_in_process("lerobot-iupe-relabel", *args, check=True)  # the next run cleans up the dead run's staged copy
    assert hidden_siblings(root) == []
    assert "relabelled_by" in json.loads((root / "meta" / "iupe.json").read_text())


def test_hub_dataset_is_pulled_relabelled_and_pushed_with_its_card(cartpole_run, cartpole_expert, tmp_path):
    with LocalHub() as hub:
        env = hub_env(hub.url, tmp_path)
        run_cli("lerobot-iupe-push", f"--dataset.root={cartpole_expert}", "--dataset.repo_id=me/demos", env=env)
        run_cli(
            "lerobot-iupe-relabel",
            f"--policy.path={cartpole_run / CHECKPOINT}",
            "--dataset.repo_id=me/demos",
            "--dataset.push_to_hub=true",
            env=env,
        )
        assert (tmp_path / "lerobot" / "me" / "demos" / "meta" / "iupe.json").exists()  # the pulled local copy
        repo = hub.repos["me/demos"]
        files = repo.snapshots[repo.tags["v3.0"]]
        card = files["README.md"].decode()
        assert "labelled by an inverse" in card and "lerobot-iupe-relabel" in card
        info = json.loads(files["meta/info.json"])
        assert info["features"]["action"]["info"]["labelled_by"] == str(cartpole_run / CHECKPOINT)


def test_one_writer_per_dataset_a_second_relabel_or_collect_stops_at_once(cartpole_run, data_dir, tmp_path):
    _, root = labelled_and_stripped(data_dir, "cartpole-relabel", "--env.type=cartpole", "--episodes=2")
    args = relabel_args(cartpole_run / CHECKPOINT, root)
    # the first writer: the real command, held once its labels are computed until this test lets it write
    code = (
        "import sys; from lerobot_iupe.relabel import run;"
        "write = run.write_labels;"
        "run.write_labels = lambda *a: (print('writing', flush=True), sys.stdin.readline(), write(*a));"
        "from lerobot_iupe.cli.relabel import main; sys.argv[1:] = sys.argv[2:]; main()"
    )
    first = subprocess.Popen(
        [sys.executable, "-c", code, "relabel", *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert any(line.strip() == "writing" for line in first.stdout)  # (LeRobot prints its own lines first)
        before = tree_digest(root)
        second = run_in_process("lerobot-iupe-relabel", *args, check=False)
        assert second.returncode == 2
        assert f"being written by another process (PID {first.pid})" in one_error_line(second)
        collect = run_in_process(
            "lerobot-iupe-collect", "--env.type=cartpole", "--episodes=1", "--overwrite=true",
            f"--dataset.repo_id=local/{root.name}", f"--dataset.root={root}", check=False,
        )  # fmt: skip
        assert collect.returncode == 2 and f"(PID {first.pid})" in one_error_line(collect)
        assert tree_digest(root) == before
    finally:
        first.communicate("go\n", timeout=300)
    assert first.returncode == 0
    assert "relabelled_by" in read_iupe_meta(root) and hidden_siblings(root) == []  # the first writer finished


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_kill_9_of_a_relabel_takes_its_worker_processes_with_it(cartpole_run, cartpole_random, tmp_path):
    """The real command with two workers, killed with SIGKILL while its workers decode and label 400 episodes: ten
    seconds later no worker is left (they block on a full queue that nobody reads, so they would sleep forever)."""
    pids = tmp_path / "workers.json"
    args = relabel_args(cartpole_run / CHECKPOINT, cartpole_random, "--dry_run=true", "--num_workers=2")
    code = f"""
import json, os, signal, sys
from lerobot_iupe.relabel import labelling

def killed(queue, processes):
    open({str(pids)!r}, "w").write(json.dumps([p.pid for p in processes]))
    os.kill(os.getpid(), signal.SIGKILL)

labelling._next_decoded = killed
from lerobot_iupe.cli.relabel import main
sys.argv[1:] = sys.argv[2:]
main()
"""
    log = tmp_path / "relabel.log"  # a file, not a pipe: an orphaned worker would hold a pipe open
    with open(log, "w") as output:
        process = subprocess.run([sys.executable, "-c", code, "relabel", *args], stdout=output, stderr=output)
    assert process.returncode == -signal.SIGKILL, log.read_text()[-3000:]
    workers = json.loads(pids.read_text())
    assert len(workers) == 2
    assert still_alive_after(workers, seconds=10) == []
