"""The commands printed in README.md and docs/ against the real CLIs: every flag of every command block is one its
command knows (a renamed flag fails here), and README's three workflows run as printed."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import BIN, run_in_process
from hub_server import LocalHub
from test_hub import hub_env

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PROGRAMS = {"lerobot-train", "lerobot-eval", "torchrun"} | {p.name for p in BIN.glob("lerobot-iupe-*")}
# Flags LeRobot's own parser takes before draccus sees the rest (lerobot/configs/parser.py), so --help lists none.
PARSER_FLAGS = {"--policy.path", "--config_path"}
SELECTORS = ("--policy.type", "--env.type")


def bash_blocks(text: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", text, flags=re.S)


def commands(block: str) -> list[list[str]]:
    """Each command of a block: continuation lines joined, comments dropped, split as the shell would."""
    joined = re.sub(r"\\\n\s*", " ", block)
    found = []
    for line in joined.splitlines():
        line = re.sub(r"(^|\s)#\s.*$", "", line).strip()
        if line:
            found.append(shlex.split(line.replace("$(which ", "").replace(")", " ")))
    return found


def program_of(words: list[str]) -> tuple[list[str], list[str]] | None:
    """The program a command runs (``python scripts/x.py`` as two words) and the words it is given, or None for a
    program this test does not know (a launcher's own flags, as torchrun's, are not the program's)."""
    for i, word in enumerate(words):
        name = Path(word).name
        if name in PROGRAMS - {"torchrun"}:
            return [name], words[i + 1 :]
        if word in ("python", "python3") and i + 1 < len(words) and words[i + 1].startswith("scripts/"):
            return ["python", words[i + 1]], words[i + 2 :]
    return None


@functools.cache
def help_text(program: tuple[str, ...], selectors: tuple[str, ...]) -> str:
    """``program``'s ``--help`` with these type selectors, run in this process (a new one per call spent ~8 s
    importing torch and LeRobot): the console script's own function, or the script as ``__main__``."""
    if program[0] != "python":
        result = run_in_process(program[0], *selectors, "--help")
        return result.stdout + result.stderr
    out, argv = io.StringIO(), sys.argv
    sys.argv = [program[1], *selectors, "--help"]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            runpy.run_path(str(ROOT / program[1]), run_name="__main__")
    except SystemExit:
        pass
    finally:
        sys.argv = argv
    return out.getvalue()


def unknown_flags(text: str) -> list[str]:
    """``command: flag`` for every flag of ``text``'s command blocks that its command's ``--help`` does not list."""
    unknown = []
    for block in bash_blocks(text):
        for words in commands(block):
            found = program_of(words)
            if found is None:
                continue
            program, arguments = found
            flags = [w.split("=", 1)[0] for w in arguments if w.startswith("--")]
            selectors = tuple(w for w in arguments if w.split("=", 1)[0] in SELECTORS)
            if "--policy.path" in flags and "--policy.type" not in flags:  # the docs' checkpoints are IUPE ones
                selectors += ("--policy.type=iupe",)
            listed = help_text(tuple(program), selectors)
            for flag in flags:
                if flag in PARSER_FLAGS or flag in SELECTORS:
                    continue
                if not re.search(rf"(^|[\s\[,]){re.escape(flag)}([\s=\],]|$)", listed, flags=re.M):
                    unknown.append(f"{' '.join(program)}: {flag}")
    return unknown


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_printed_flag_is_one_the_cli_knows(page):
    assert unknown_flags(page.read_text()) == []


def test_a_renamed_flag_is_caught():
    page = "```bash\nlerobot-iupe-relabel --policy.path=x --dataset.repo_id=local/x --dry_runs=true\n```\n"
    train = "```bash\nlerobot-train --policy.type=iupe --policy.cycle_step=100 --steps=10\n```\n"
    script = "```bash\npython scripts/make_arm_recording.py --root data/x --episode 4\n```\n"
    assert unknown_flags(page) == ["lerobot-iupe-relabel: --dry_runs"]
    assert unknown_flags(train) == ["lerobot-train: --policy.cycle_step"]
    assert unknown_flags(script) == ["python scripts/make_arm_recording.py: --episode"]


def readme_workflow(heading: str) -> str:
    """The command block under README.md's section ``heading``."""
    section = README.split(f"## {heading}", 1)[1].split("\n## ", 1)[0]
    (block,) = bash_blocks(section)
    return block


README = (ROOT / "README.md").read_text()


def run_block(block: str, cwd: Path, env: dict | None = None) -> None:
    (cwd / "scripts").exists() or (cwd / "scripts").symlink_to(ROOT / "scripts")
    path = f"{BIN}{os.pathsep}{os.environ['PATH']}"
    result = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", block], cwd=cwd, capture_output=True, text=True, timeout=900,
        env={**os.environ, "PATH": path, **(env or {})},
    )  # fmt: skip
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-5000:]}"


def test_workflows_1_and_3_run_as_printed(tmp_path):
    """Learn from state-only demonstrations and evaluate with lerobot-eval; then push and pull the expert data
    (against a local hub on 127.0.0.1)."""
    run_block(readme_workflow("1. Learn a policy from state-only demonstrations"), tmp_path)
    assert (tmp_path / "outputs/eval-cartpole/eval_info.json").exists()
    with LocalHub() as hub:
        run_block(readme_workflow("3. Share demonstration datasets"), tmp_path, hub_env(hub.url, tmp_path / "home"))
        assert "v3.0" in hub.repos["me/cartpole-expert"].tags


def test_workflow_2_runs_as_printed(tmp_path):
    """Write the recordings, train the IDM, relabel in place, and train LeRobot's ACT with action chunks on the
    result, offline (its ImageNet backbone is not downloaded)."""
    block = readme_workflow("2. Relabel a state-only (video) dataset, then train LeRobot's own policy")
    assert "--policy.n_action_steps=1 " not in block, "README's ACT must play action chunks, as users run it"
    run_block(block, tmp_path, {"HF_HUB_OFFLINE": "1"})
    info = (tmp_path / "data/arm-unlabelled/meta/info.json").read_text()
    assert '"action"' in info
    config = json.loads((tmp_path / "outputs/arm-act/checkpoints/last/pretrained_model/config.json").read_text())
    assert config["type"] == "act" and config["n_action_steps"] > 1
