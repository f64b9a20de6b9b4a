"""Policies that remember: ``--policy.n_obs_steps=n`` feeds the policy model its last n observations, in training
(windows of the expert data), in the IUPE cycle's rollouts and in ``lerobot-eval`` (``select_action``)."""

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT, run_in_process
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets import LeRobotDataset
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_iupe.data.readers import column_array
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy
from lerobot_iupe.policy.algorithm import r_squared


def continuous_policy(n_obs_steps: int) -> IUPEPolicy:
    config = IUPEConfig(
        input_features={OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(3,))},
        action_low=[-1.0, -1.0],
        action_high=[1.0, 1.0],
        n_obs_steps=n_obs_steps,
        device="cpu",
    )
    torch.manual_seed(0)
    return IUPEPolicy(config).eval()


def test_select_action_reads_the_last_n_observations_oldest_first_and_reset_forgets_them():
    policy = continuous_policy(3)
    o1, o2, o3, o4 = torch.randn(4, 5, 3)  # four steps of a batch of 5 envs

    def play(*observations):
        policy.reset()
        return [policy.select_action({OBS_STATE: o}) for o in observations][-1]

    history = lambda *frames: policy.pm_head.mode(policy.pm_history_output(torch.stack(frames, 1)))  # noqa: E731
    torch.testing.assert_close(play(o1, o2, o3, o4), history(o2, o3, o4))  # the oldest has left the window
    torch.testing.assert_close(play(o1, o2), history(o1, o1, o2))  # an episode's start repeats its first frame
    torch.testing.assert_close(play(o2), history(o2, o2, o2))  # reset: nothing of the last episode is left
    assert not torch.allclose(play(o1, o2), play(o2))  # the past changes the action
    with pytest.raises(ValueError, match="n_obs_steps"):
        policy.pm_output(o1)


def test_n_obs_steps_is_refused_below_one():
    with pytest.raises(ValueError, match="--policy.n_obs_steps must be 1 or more"):
        IUPEConfig(n_obs_steps=0)


def write_delayed_echo(root, episodes: int, seed: int) -> None:
    """Each action repeats the observation before it (a_t = s_{t-1}[0]; a_0 = s_0[0]), states drawn at random:
    the current observation alone says nothing about the action."""
    rng = np.random.default_rng(seed)
    features = {
        OBS_STATE: {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        ACTION: {"dtype": "float32", "shape": (1,), "names": ["echo"]},
    }
    dataset = LeRobotDataset.create(f"local/{root.name}", 10, features, root=root, use_videos=False)
    for _ in range(episodes):
        previous = None
        for _ in range(40):
            state = rng.uniform(-1, 1, 2).astype(np.float32)
            action = (state if previous is None else previous)[:1]
            dataset.add_frame({OBS_STATE: state, ACTION: action.copy(), "task": "echo"})
            previous = state
        dataset.save_episode()
    dataset.finalize()


def test_a_policy_with_history_learns_what_the_current_observation_cannot_tell(tmp_path):
    data = tmp_path / "echo"
    write_delayed_echo(data, episodes=30, seed=0)
    scores = {}
    for n in (1, 2):
        out = tmp_path / f"bc-{n}"
        run_in_process(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true", f"--dataset.repo_id=local/{data.name}",
            f"--dataset.root={data}", f"--output_dir={out}", "--num_workers=0", "--policy.device=cpu",
            "--wandb.enable=false", "--steps=150", "--save_freq=150", "--batch_size=64", f"--policy.n_obs_steps={n}",
            check=True,
        )  # fmt: skip
        policy = IUPEPolicy.from_pretrained(out / CHECKPOINT).eval()
        assert policy.config.n_obs_steps == n
        dataset = LeRobotDataset("local/echo", root=data)
        states, actions, episodes = (column_array(dataset.hf_dataset, k) for k in (OBS_STATE, ACTION, "episode_index"))
        played = []
        for episode in np.unique(episodes):  # LeRobot's env loop: reset, then one select_action per step
            policy.reset()
            rows = np.flatnonzero(episodes == episode)
            played += [policy.select_action({OBS_STATE: torch.as_tensor(states[r : r + 1])})[0].numpy() for r in rows]
        scores[n] = r_squared(np.array(played), actions)
    assert scores[2] > 0.9, scores  # trained on windows and played with the same history, oldest first
    assert scores[1] < 0.2, scores  # the current observation alone cannot


def test_the_idm_can_read_some_observation_keys_only():
    features = {
        OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(3,)),
        "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(2,)),
    }
    config = IUPEConfig(
        input_features=features, action_low=[-1.0], action_high=[1.0], idm_observation_keys=[OBS_STATE], device="cpu"
    )
    torch.manual_seed(0)
    policy = IUPEPolicy(config).eval()
    window = torch.randn(4, 2, 5)
    moved = window.clone()
    moved[..., 3:] += 10.0  # the environment state changes; the IDM must not see it
    torch.testing.assert_close(policy.idm_window_output(moved), policy.idm_window_output(window))
    moved[..., :3] += 1.0
    assert not torch.allclose(policy.idm_window_output(moved), policy.idm_window_output(window))
    acted = []
    for shift in (0.0, 1.0):  # the policy model still reads everything
        policy.reset()
        observation = {OBS_STATE: window[:, 0, :3], "observation.environment_state": window[:, 0, 3:] + shift}
        acted.append(policy.select_action(observation))
    assert not torch.allclose(*acted)
    with pytest.raises(ValueError, match="--policy.idm_observation_keys"):
        IUPEConfig(input_features=features, action_low=[-1.0], action_high=[1.0],
                   idm_observation_keys=["observation.images.top"]).validate_features()  # fmt: skip
