"""Hub: push a dataset root with its filled card; pulling is plain ``LeRobotDataset(repo_id)``."""

from __future__ import annotations

import contextlib
from importlib import resources
from pathlib import Path

from huggingface_hub import DatasetCard, DatasetCardData, HfApi, constants
from huggingface_hub.errors import RevisionNotFoundError
from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.datasets.dataset_metadata import CODEBASE_VERSION
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

from lerobot_iupe.data.storage import is_dataset, read_iupe_meta
from lerobot_iupe.envs.configs import env_config_from_settings
from lerobot_iupe.errors import CommandError

# Package data (datasets_cards/ at the repository's top level links to it), so a wheel install can push.
CARD_TEMPLATE = resources.files("lerobot_iupe") / "assets" / "iupe_demonstrations.md"
CARD_TAGS = ["LeRobot", "imitation-from-observation", "iupe"]
AGENT_DESCRIPTIONS = {
    "expert": "the package's built-in expert",
    "random": "uniform-random actions (pre-demonstrations for the inverse dynamics model)",
    "play": "goal-agnostic play: random reachable targets and gripper commands, never reading the task's objects "
    "(pre-demonstrations for the inverse dynamics model)",
}


class HubError(CommandError):
    """The hub refused or could not be reached; the local dataset is untouched."""


def build_card(root: str | Path, repo_id: str, license: str = "apache-2.0") -> DatasetCard:
    """Fill the package's card template from the dataset's metadata."""
    info = LeRobotDatasetMetadata(repo_id, root=root).info
    meta = read_iupe_meta(root)
    obs_keys = [k for k in info.features if k.startswith("observation.")]
    obs_key = OBS_IMAGE if OBS_IMAGE in info.features else OBS_STATE if OBS_STATE in info.features else obs_keys[0]
    action = info.features.get(ACTION)
    if action is not None and action["dtype"].startswith("float"):
        action_text = f"float32 {tuple(action['shape'])}: {', '.join(action['names'] or [])}"
    else:
        n_actions = getattr(env_config_from_settings(meta["env"]), "n_actions", "?") if "env" in meta else "?"
        action_text = f"int64 action id, {n_actions} actions"
    observation_text = ", ".join(
        f"`{k}` {tuple(info.features[k]['shape'])}"
        + (" (stored as video)" if info.features[k]["dtype"] == "video" else "")
        for k in obs_keys
    )
    env = meta.get("env") or {"type": info.robot_type or "unknown"}
    seeds = meta.get("seeds", [0])
    tags = CARD_TAGS + ([env["type"]] if env["type"] != "unknown" else [])
    card_data = DatasetCardData(license=license, task_categories=["robotics"], tags=tags)
    if "agent" in meta:
        command = (
            f"lerobot-iupe-collect --env.type={env['type']} --agent={meta.get('agent')} "
            f"--episodes={meta.get('episodes')} --seed={seeds[0]} --dataset.repo_id={repo_id}"
        )
    else:  # a dataset recorded elsewhere (e.g. by LeRobot itself) and only relabelled here
        command = "# recorded outside lerobot_iupe; its actions were labelled with lerobot-iupe-relabel"
    if env["type"] == "maze":
        command += f" --env.size={env['size']} --env.image_size={env['image_size']}"
    return DatasetCard.from_template(
        card_data,
        template_path=str(CARD_TEMPLATE),
        repo_id=repo_id,
        env_name=env["type"] + (f" {env['size']}x{env['size']}" if "size" in env else ""),
        agent=meta.get("agent", "unknown"),
        agent_title=str(meta.get("agent", "")).capitalize(),
        agent_description=AGENT_DESCRIPTIONS.get(meta.get("agent"), "unknown"),
        episodes=info.total_episodes,
        frames=info.total_frames,
        fps=info.fps,
        first_seed=seeds[0],
        last_seed=seeds[-1],
        observation_key=obs_key,
        observation_shape=tuple(info.features[obs_key]["shape"]),
        is_video=info.features[obs_key]["dtype"] == "video",
        has_actions=ACTION in info.features,
        relabelled_by=meta.get("relabelled_by"),
        action_text=action_text,
        observation_text=observation_text,
        env_settings=env,
        mean_return=f"{meta.get('mean_return', float('nan')):.2f}",
        std_return=f"{meta.get('std_return', float('nan')):.2f}",
        success_rate=f"{meta.get('success_rate', float('nan')):.0%}",
        collect_command=command,
        collected="agent" in meta,
    )


def push_dataset(root: str | Path, repo_id: str, private: bool = False, license: str = "apache-2.0") -> str:
    """Upload a complete local dataset with its filled card as README.md and tag it with LeRobot's codebase
    version (``v3.0``), which ``LeRobotDataset(repo_id)`` needs to pull it.

    These are the steps of ``LeRobotDataset.push_to_hub`` done with ``HfApi`` directly: LeRobot's version
    validates its own card against huggingface.co (a hard-coded URL), so it fails on any other ``HF_ENDPOINT``."""
    root = Path(root)
    if not is_dataset(root):
        raise FileNotFoundError(f"--dataset.root={root} is not a LeRobot dataset (no meta/info.json)")
    card = build_card(root, repo_id, license)
    api = HfApi()
    try:
        api.create_repo(repo_id, repo_type="dataset", private=private, exist_ok=True)
        api.upload_folder(
            repo_id=repo_id,
            folder_path=root,
            repo_type="dataset",
            ignore_patterns=["images/"],
            commit_message="Upload dataset with lerobot_iupe",
        )
        api.upload_file(
            path_or_fileobj=str(card).encode(),
            path_in_repo="README.md",
            repo_id=repo_id,
            repo_type="dataset",
            commit_message="Dataset card from lerobot_iupe",
        )
        with contextlib.suppress(RevisionNotFoundError):
            api.delete_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
        api.create_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
    except Exception as error:  # httpx and huggingface_hub raise many types; the message is what matters
        raise HubError(
            f"pushing {root} to the hub as {repo_id} failed ({type(error).__name__}: {error}); "
            "the local dataset is unchanged — check HF_ENDPOINT, your token (hf auth login) and the repo id"
        ) from error
    return f"{constants.ENDPOINT}/datasets/{repo_id}"
