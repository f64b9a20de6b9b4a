"""`--help` explains every flag the package defines: each has at least one sentence (draccus takes it from the
comment above the field), for the package's CLIs and for the options its policies add to lerobot-train."""

import dataclasses
import re

import pytest
from conftest import run_in_process
from lerobot.configs import PreTrainedConfig

from lerobot_iupe.ilpo import ILPOConfig
from lerobot_iupe.policy import IUPEConfig

FLAG = re.compile(r"^ {2}(--[\w.]+)(?: (?:\[\w+\]|\{[^}]*\}|\w+))?(?: {2,}(.*))?$")


def described_flags(text: str) -> dict[str, str]:
    """Each ``--flag`` of a help text and its description (continuation lines joined)."""
    flags, current = {}, None
    for line in text.splitlines():
        match = FLAG.match(line)
        if match:
            current = match.group(1)
            flags[current] = (match.group(2) or "").strip()
        elif current and line.startswith(" " * 10) and line.strip():
            flags[current] = f"{flags[current]} {line.strip()}".strip()
        else:
            current = None
    return flags


def undescribed(text: str, wanted=None) -> list[str]:
    flags = described_flags(text)
    assert flags, text[:2000]
    return sorted(f for f, words in flags.items() if (wanted is None or f in wanted) and not words)


@pytest.mark.parametrize("command", ["lerobot-iupe-collect", "lerobot-iupe-relabel", "lerobot-iupe-push"])
def test_every_flag_of_the_packages_commands_is_explained(command):
    result = run_in_process(command, "--help")
    assert undescribed(result.stdout + result.stderr) == []


@pytest.mark.parametrize("config", [IUPEConfig, ILPOConfig])
def test_every_option_a_policy_adds_to_lerobot_train_is_explained(config):
    base = {f.name for f in dataclasses.fields(PreTrainedConfig)}
    ours = {f"--policy.{f.name}" for f in dataclasses.fields(config) if f.name not in base}
    text = run_in_process("lerobot-train", f"--policy.type={PreTrainedConfig.get_choice_name(config)}", "--help")
    missing = undescribed(text.stdout + text.stderr, ours)
    assert missing == []
