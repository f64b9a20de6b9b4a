import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from conftest import run_cli, run_in_process
from hub_server import LocalHub
from lerobot.datasets import LeRobotDataset


def hub_env(url: str, home) -> dict:
    return {
        "HF_ENDPOINT": url,
        "HF_TOKEN": "hf_local_test",
        "HF_LEROBOT_HOME": str(home / "lerobot"),
        "HF_HOME": str(home / "hf"),
        "HF_HUB_DISABLE_TELEMETRY": "1",
    }


def test_push_and_pull_round_trip(cartpole_expert, tmp_path):
    with LocalHub() as hub:
        env = hub_env(hub.url, tmp_path)
        run_cli("lerobot-iupe-push", f"--dataset.root={cartpole_expert}", "--dataset.repo_id=me/cartpole", env=env)
        repo = hub.repos["me/cartpole"]
        assert "v3.0" in repo.tags
        files = repo.snapshots[repo.tags["v3.0"]]
        card = files["README.md"].decode()
        assert "imitation-from-observation" in card and "task_categories" in card and "robotics" in card
        code = (
            "from lerobot.datasets import LeRobotDataset; import torch, sys;"
            "d = LeRobotDataset('me/cartpole');"
            f"local = LeRobotDataset('local/cartpole-expert', root=r'{cartpole_expert}');"
            "assert len(d) == len(local);"
            "key = 'observation.state';"
            "assert all(torch.equal(d[i][key], local[i][key]) for i in range(0, len(d), 97));"
            "print('ROOT', d.root)"
        )
        result = subprocess.run([sys.executable, "-c", code], env={**os.environ, **env}, capture_output=True, text=True)
        assert result.returncode == 0, result.stderr[-3000:]
        assert str(tmp_path / "lerobot") in result.stdout  # pulled into the empty cache


@pytest.mark.parametrize("failure", ["refused", "unreachable"])
def test_hub_failure_is_reported_and_local_dataset_is_intact(cartpole_expert, tmp_path, failure):
    before = {p: p.read_bytes() for p in cartpole_expert.rglob("*") if p.is_file()}
    with LocalHub() as hub:
        hub.refuse = failure == "refused"
        url = hub.url if failure == "refused" else "http://127.0.0.1:9"
        result = run_cli(
            "lerobot-iupe-push",
            f"--dataset.root={cartpole_expert}",
            "--dataset.repo_id=me/cp",
            env=hub_env(url, tmp_path),
            check=False,
        )
    assert result.returncode == 2
    assert "pushing" in result.stderr and "local dataset is unchanged" in result.stderr
    assert {p: p.read_bytes() for p in cartpole_expert.rglob("*") if p.is_file()} == before
    assert LeRobotDataset("local/cartpole-expert", root=cartpole_expert).meta.total_episodes == 10


def test_collect_with_push_to_hub(tmp_path):
    with LocalHub() as hub:
        root = tmp_path / "acro"
        run_cli(
            "lerobot-iupe-collect",
            "--env.type=acrobot",
            "--agent=random",
            "--episodes=1",
            "--dataset.push_to_hub=true",
            "--dataset.repo_id=me/acrobot-random",
            f"--dataset.root={root}",
            env=hub_env(hub.url, tmp_path),
        )
        assert "meta/iupe.json" in hub.repos["me/acrobot-random"].snapshots[hub.repos["me/acrobot-random"].tags["v3.0"]]


def test_push_of_a_non_dataset_is_refused(tmp_path):
    result = run_in_process("lerobot-iupe-push", f"--dataset.root={tmp_path}", "--dataset.repo_id=me/x")
    assert result.returncode == 2 and "is not a LeRobot dataset" in result.stderr


def test_push_works_from_a_wheel_installed_in_a_fresh_venv(cartpole_expert, tmp_path):
    """The card template ships inside the wheel: a normal (non-editable) install can push."""
    repo = Path(__file__).resolve().parents[1]
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "lerobot_policy_iupe.py"):
        shutil.copy(repo / name, source / name)
    shutil.copytree(repo / "lerobot_iupe", source / "lerobot_iupe", ignore=shutil.ignore_patterns("__pycache__"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", tmp_path / "wheels", source], check=True)
    venv = tmp_path / "fresh"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True)
    site = venv / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    wheel = next((tmp_path / "wheels").glob("lerobot_policy_iupe-*.whl"))
    subprocess.run([*pip, "install", "--no-deps", "--target", site, wheel], check=True)
    # dependencies (lerobot, torch, …) from the test venv; its editable install of this package is not seen
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    code = (
        "import sys, lerobot_iupe; print('PACKAGE', lerobot_iupe.__file__);"
        "from lerobot_iupe.cli.push import main; sys.argv[1:] = sys.argv[2:]; main()"
    )
    with LocalHub() as hub:
        result = subprocess.run(
            [
                venv / "bin" / "python",
                "-c",
                code,
                "push",
                f"--dataset.root={cartpole_expert}",
                "--dataset.repo_id=me/w",
            ],
            cwd=tmp_path,
            env={**os.environ, **hub_env(hub.url, tmp_path)},
            capture_output=True,
            text=True,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        assert f"PACKAGE {site}" in result.stdout
        card = hub.repos["me/w"].snapshots[hub.repos["me/w"].tags["v3.0"]]["README.md"].decode()
        assert "imitation-from-observation" in card
