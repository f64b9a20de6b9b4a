import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.datasets import LeRobotDataset

from lerobot_iupe.data.readers import ExpertFrames, column_array, load_transitions
from lerobot_iupe.data.transitions import Transitions, context_offsets
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy, threads
from lerobot_iupe.policy.idm_fit import fit_idm
from lerobot_iupe.policy.networks import SpatialSelfAttention, TokenSelfAttention


def test_token_attention_is_identity_at_gamma_zero_and_mixes_positions_otherwise():
    torch.manual_seed(0)
    attention = TokenSelfAttention(8)
    x = torch.randn(3, 5, 8)
    assert torch.equal(attention(x), x)
    with torch.no_grad():
        attention.gamma.fill_(1.0)
    y = attention(x)
    x2 = x.clone()
    x2[:, 4] += 1.0  # change only the last position
    assert not torch.allclose(attention(x2)[:, 0], y[:, 0])  # the first position's output moved too


def test_spatial_attention_is_identity_at_gamma_zero_and_mixes_positions_otherwise():
    torch.manual_seed(0)
    attention = SpatialSelfAttention(8)
    x = torch.randn(2, 8, 4, 4)
    assert torch.equal(attention(x), x)
    with torch.no_grad():
        attention.gamma.fill_(1.0)
    x2 = x.clone()
    x2[:, :, 3, 3] += 1.0
    assert not torch.allclose(attention(x2)[:, :, 0, 0], attention(x)[:, :, 0, 0])


def make_policy(image: bool, **overrides) -> IUPEPolicy:
    key, shape = ("observation.image", (3, 64, 64)) if image else ("observation.state", (4,))
    ftype = FeatureType.VISUAL if image else FeatureType.STATE
    config = IUPEConfig(
        input_features={key: PolicyFeature(type=ftype, shape=shape)},
        n_actions=4 if image else 2,
        env_settings={"type": "maze", "size": 3} if image else {"type": "cartpole"},
        device="cpu",
        **overrides,
    )
    return IUPEPolicy(config)


def test_save_load_gives_identical_actions(tmp_path):
    for image in (False, True):
        torch.manual_seed(1)
        policy = make_policy(image)
        key = policy.config.observation_key
        obs = torch.rand(6, *policy.config.input_features[key].shape)
        torch.manual_seed(5)
        actions = policy.select_action({key: obs})
        assert actions.shape == (6, 1)
        policy.save_pretrained(tmp_path / str(image))
        loaded = IUPEPolicy.from_pretrained(tmp_path / str(image))
        torch.manual_seed(5)
        assert torch.equal(loaded.select_action({key: obs}), actions)
        assert loaded.config.n_actions == policy.config.n_actions


def test_idm_and_pm_output_one_logit_per_action():
    policy = make_policy(image=True)
    s, s_next = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    assert policy.idm_output(s, s_next).shape == (2, 4)
    assert policy.pm_output(s).shape == (2, 4)


def test_resnet18_backbone_builds_and_runs():
    policy = make_policy(image=True, image_backbone="resnet18")
    policy.eval()
    s = torch.rand(2, 3, 64, 64)
    assert policy.idm_output(s, s).shape == (2, 4) and policy.pm_output(s).shape == (2, 4)
    assert policy.pm_encoder.attention1.gamma.item() == 0.0


@pytest.mark.parametrize("exploration", [False, True])
def test_select_action_follows_eval_mode_whatever_the_training_switches(exploration):
    obs = {"observation.state": torch.randn(256, 4)}
    greedy = make_policy(image=False, exploration=exploration)
    with torch.no_grad():
        greedy.pm_head.weight.mul_(0)  # uniform-ish logits: sampling would disagree with the argmax often
        argmax = greedy.pm_output(obs["observation.state"]).argmax(-1).float()
    assert torch.equal(greedy.select_action(obs)[:, 0], argmax)
    sampling = make_policy(image=False, exploration=not exploration, eval_mode="sample")
    sampling.load_state_dict(greedy.state_dict())
    torch.manual_seed(0)
    assert not torch.equal(sampling.select_action(obs)[:, 0], argmax)


def test_expert_frames_give_successive_states_by_frame_index(cartpole_expert):
    dataset = LeRobotDataset("local/cartpole-expert", root=cartpole_expert)
    expert = ExpertFrames(dataset, "observation.state", with_actions=False, device=torch.device("cpu"))
    states = column_array(dataset.hf_dataset, "observation.state")
    first_episode_end = int(dataset.meta.episodes["dataset_to_index"][0])
    rows = expert.rows(torch.tensor([0, 5, first_episode_end - 2]))
    state, next_state = expert.pairs(rows)
    assert np.array_equal(state.numpy(), states[[0, 5, first_episode_end - 2]])
    assert np.array_equal(next_state.numpy(), states[[1, 6, first_episode_end - 1]])
    with pytest.raises(ValueError, match="last of its episode"):
        expert.pairs(expert.rows(torch.tensor([first_episode_end - 1])))
    with pytest.raises(KeyError, match="not in the expert dataset"):
        expert.rows(torch.tensor([len(states)]))


def test_pre_demonstration_windows_are_the_rollouts_and_the_expert_windows(cartpole_random):
    """One window rule for the IDM's three sources: a dataset read by load_transitions, an episode played
    (Transitions.of_episode) and the expert frames it labels (ExpertFrames.transition_windows)."""
    dataset = LeRobotDataset("local/cartpole-random", root=cartpole_random)
    states = column_array(dataset.hf_dataset, "observation.state")
    actions = column_array(dataset.hf_dataset, "action").reshape(-1)
    episodes = dataset.meta.episodes
    bounds = list(zip(episodes["dataset_from_index"], episodes["dataset_to_index"], strict=True))
    loaded = load_transitions(dataset, "observation.state", context=2)
    played = Transitions.concat([Transitions.of_episode(states[a:b], actions[a : b - 1], 2) for a, b in bounds])
    assert loaded.windows.shape == (len(states) - len(bounds), 6, 4)
    assert np.array_equal(loaded.windows, played.windows) and np.array_equal(loaded.actions, played.actions)
    expert = ExpertFrames(dataset, "observation.state", with_actions=False, device=torch.device("cpu"))
    a, b = bounds[0]
    rows = np.array([0, b - 2, b])  # an episode's first frame, its last with a successor, the next one's first
    windows = expert.transition_windows(rows, context_offsets(2)).numpy()
    assert np.array_equal(windows, loaded.windows[[0, b - 2, b - 1]])
    assert np.array_equal(windows[1], states[[b - 4, b - 3, b - 2, b - 1, b - 1, b - 1]])  # edges repeat, never cross


def test_a_windowed_idm_in_the_cycle_reads_an_action_that_shows_one_step_late():
    """fit_idm on windowed transitions: where a_t first moves s_{t+2}, the pair (s_t, s_{t+1}) labels it at chance
    and the window t-1 … t+2 labels it exactly."""
    rng = np.random.default_rng(0)

    def lagged_episodes(context: int) -> Transitions:
        episodes = []
        for _ in range(40):
            actions = rng.integers(0, 2, size=50)
            moves = np.r_[0.0, 2.0 * actions[:-1] - 1.0]  # s_{t+1} - s_t = the previous step's action
            observations = np.zeros((51, 4), dtype=np.float32)
            observations[1:, 0] = np.cumsum(moves)
            observations[:, 1:] = rng.normal(size=(51, 3))
            episodes.append(Transitions.of_episode(observations, actions, context))
        return Transitions.concat(episodes)

    scores = {}
    for context in (0, 1):
        torch.manual_seed(0)
        policy = make_policy(image=False, idm_context=context, idm_epochs=8, idm_batch_size=64)
        optimizer = torch.optim.Adam(policy.idm_parameters(), lr=3e-3)
        _, scores[context] = fit_idm(policy, optimizer, lagged_episodes(context), lagged_episodes(context), rng)
    assert scores[0] < 0.65 and scores[1] > 0.95, scores


def test_unknown_eval_mode_is_refused_naming_the_flag():
    with pytest.raises(ValueError, match=r"--policy.eval_mode must be one of \['argmax', 'sample'\], got 'greedy'"):
        IUPEConfig(eval_mode="greedy")


def test_unknown_image_backbone_is_refused_naming_the_flag():
    with pytest.raises(ValueError, match=r"--policy.image_backbone must be one of \['cnn', 'resnet18'\], got 'vit'"):
        IUPEConfig(image_backbone="vit")


FREE_64_MB = """
import importlib.util, os, sys
import numpy as np
spec = importlib.util.spec_from_file_location("threads", sys.argv[1])  # the module alone: not the policy's imports
threads = importlib.util.module_from_spec(spec)
spec.loader.exec_module(threads)
def retained():
    resident = lambda: int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    before = resident()
    block = np.ones(64 << 20, dtype=np.uint8)
    del block
    return resident() - before
print(retained(), threads.keep_freed_memory(), retained())
"""


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="reads resident memory from /proc")
def test_freed_blocks_go_back_by_default_and_stay_with_a_process_that_keeps_freed_memory():
    """An IDM batch's tensors are freed and allocated again at the same size every pass; glibc unmaps blocks over
    32 MB when freed, so each pass page-faulted them in afresh. ``keep_freed_memory`` keeps them (relabelling and
    training call it); the setting is the process's, so the test runs in one of its own."""
    module = Path(threads.__file__)
    run = subprocess.run([sys.executable, "-c", FREE_64_MB, str(module)], capture_output=True, text=True, check=True)
    by_default, kept, after = run.stdout.split()
    assert int(by_default) < 16 << 20
    assert kept == "True" and int(after) > 48 << 20
