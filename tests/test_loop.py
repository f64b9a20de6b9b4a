"""The IUPE cycle in process, on real datasets and real envs, stepped as lerobot-train steps it
(forward → backward → clip → optimizer step → zero_grad → update)."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import CHECKPOINT
from lerobot.datasets import LeRobotDatasetMetadata
from lerobot.policies import make_policy
from safetensors.torch import load_file

import lerobot_iupe.policy.rollouts as rollouts
import lerobot_iupe.policy.training as training
from lerobot_iupe.data.storage import read_iupe_meta
from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.policy import IUPEConfig, IUPEPolicy
from lerobot_iupe.policy.algorithm import held_out_split
from lerobot_iupe.policy.training import TRAINING_STATE_FILE


def build(expert: Path, pre: Path, **overrides) -> IUPEPolicy:
    meta = LeRobotDatasetMetadata(f"local/{expert.name}", root=expert)
    settings = {"seed": 0, "rollout_episodes": 4, "cycle_steps": 2, "idm_epochs": 1, **overrides}
    config = IUPEConfig(pre_demos_repo_id=f"local/{pre.name}", pre_demos_root=str(pre), device="cpu", **settings)
    torch.manual_seed(0)  # as lerobot-train seeds before building the policy: its weights must not follow test order
    return make_policy(config, ds_meta=meta)


def frame_batch(expert: Path, size: int, seed: int = 0) -> dict:
    """A batch as LeRobot's sampler gives it: frame indices, never an episode's last frame."""
    episodes = LeRobotDatasetMetadata(f"local/{expert.name}", root=expert).episodes
    frames = np.concatenate(
        [np.arange(a, b - 1) for a, b in zip(episodes["dataset_from_index"], episodes["dataset_to_index"], strict=True)]
    )
    return {"index": torch.as_tensor(np.random.default_rng(seed).choice(frames, size))}


def train_steps(policy: IUPEPolicy, expert: Path, steps: int, optimizer=None) -> torch.optim.Optimizer:
    optimizer = optimizer or torch.optim.Adam(policy.get_optim_params(), lr=1e-3)
    policy.train()
    for step in range(steps):
        loss, _ = policy.forward(frame_batch(expert, 16, step))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        optimizer.step()
        optimizer.zero_grad()
        policy.update()
    return optimizer


def non_policy_gradients(policy: IUPEPolicy) -> list[str]:
    optimised = {id(p) for p in policy.get_optim_params()}
    return [name for name, p in policy.named_parameters() if id(p) not in optimised and p.grad is not None]


def test_a_policy_built_from_python_never_reads_the_command_line(cartpole_expert, cartpole_random, monkeypatch):
    # a notebook or another tool's CLI: its arguments are not lerobot-train's
    monkeypatch.setattr("sys.argv", ["some-tool", "--env.type=acrobot", "--env.episode_length=7"])
    assert build(cartpole_expert, cartpole_random).config.env_settings == read_iupe_meta(cartpole_expert)["env"]
    given = {"type": "cartpole", "episode_length": 77}
    assert build(cartpole_expert, cartpole_random, env_settings=given).config.env_settings == given


def test_after_a_step_only_the_policy_model_carries_gradients(cartpole_expert, cartpole_random):
    policy = build(cartpole_expert, cartpole_random)
    loss, _ = policy.forward(frame_batch(cartpole_expert, 16))  # the first step trains the IDM on I_pre
    loss.backward()
    assert non_policy_gradients(policy) == []  # what lerobot-train clips and logs as grdn
    optimizer = torch.optim.Adam(policy.get_optim_params())
    optimizer.step()
    optimizer.zero_grad()
    policy.update()
    train_steps(policy, cartpole_expert, 1, optimizer)  # ends a cycle: rollouts, I^s, IDM retrained
    assert len(policy.cycles) == 1
    policy.forward(frame_batch(cartpole_expert, 16))[0].backward()
    assert non_policy_gradients(policy) == []


def test_idm_labels_in_eval_mode_leave_batch_norm_statistics_alone(maze_expert, maze_random):
    policy = build(maze_expert, maze_random, image_backbone="resnet18", idm_batch_size=32)
    policy.train()
    policy.forward(frame_batch(maze_expert, 8))  # starts training: the IDM learns I_pre in train mode
    before = {k: v.clone() for k, v in policy.idm_encoder.state_dict().items() if "running" in k}
    assert before
    policy.forward(frame_batch(maze_expert, 8, seed=1))  # labels a batch of expert pairs
    after = {k: v for k, v in policy.idm_encoder.state_dict().items() if "running" in k}
    assert all(torch.equal(before[k], after[k]) for k in before)


def test_building_a_policy_leaves_the_process_thread_count_alone(cartpole_run, cartpole_expert, cartpole_random):
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        loaded = IUPEPolicy.from_pretrained(cartpole_run / CHECKPOINT)  # as lerobot-eval and relabelling do
        policy = build(cartpole_expert, cartpole_random)
        assert torch.get_num_threads() == 2
        # lerobot-eval's select_action: the vector policy acts on 1 thread and gives the caller its 2 back
        acting = []
        loaded.pm_encoder.register_forward_pre_hook(lambda *_: acting.append(torch.get_num_threads()))
        loaded.eval().select_action({"observation.state": torch.zeros(3, 4)})
        assert acting == [1] and torch.get_num_threads() == 2
        policy.forward(frame_batch(cartpole_expert, 16))  # training starts: vector policies train on 1 thread
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)


def row_keys(data: Transitions) -> list[bytes]:
    parts = zip(data.states, data.actions, data.next_states, strict=True)
    return [state.tobytes() + action.tobytes() + after.tobytes() for state, action, after in parts]


def sorted_rows(data: Transitions) -> list[bytes]:
    return sorted(row_keys(data))


class Spy:
    """Records a real function's arguments and result."""

    def __init__(self, function):
        self.function, self.calls = function, []

    def __call__(self, *args, **kwargs):
        result = self.function(*args, **kwargs)
        self.calls.append((args, kwargs, result))
        return result


def test_the_cycle_samples_from_successful_runs_only_and_keeps_the_selected_model(
    maze_expert, maze_random, monkeypatch, tmp_path
):
    policy = build(maze_expert, maze_random, rollout_episodes=8)
    sampled_sets = Spy(training.build_sampled_set)
    monkeypatch.setattr(training, "build_sampled_set", sampled_sets)
    rollouts = Spy(policy.trainer.rollout)
    monkeypatch.setattr(policy.trainer, "rollout", rollouts)
    idm_trainings = Spy(policy.trainer.train_idm)
    monkeypatch.setattr(policy.trainer, "train_idm", idm_trainings)
    selected_pm = None
    optimizer = None
    for _ in range(3):
        optimizer = train_steps(policy, maze_expert, 2, optimizer)
        if policy.cycles[-1]["selected"]:
            selected_pm = {k: v.clone() for k, v in policy.state_dict().items() if k.startswith("pm_")}
    pre, pre_held = policy.trainer.state.pre, policy.trainer.state.pre_held
    n_pre = len(pre) + len(pre_held)
    assert len(pre_held) == n_pre // 10
    assert idm_trainings.calls[0][0] == (pre, pre_held)  # the first IDM: I_pre less its held-out tenth
    # each cycle: 8 drawing rollouts, then 8 episodes of its own by the argmax (as lerobot-eval plays) from the same
    # start seeds every cycle, whose rates select the model
    drawing = [c for c in rollouts.calls if c[1]["explore"]]
    selecting = [c for c in rollouts.calls if not c[1]["explore"]]
    assert len(drawing) == len(selecting) == 3 and len({c[0] for c in selecting}) == 1
    for cycle, (_, _, (_, goals, _, env_successes)) in zip(policy.cycles, selecting, strict=True):
        assert cycle["selection_episodes"] == len(goals) == 8
        assert (cycle["selection_env_success_rate"], cycle["selection_goal_rate"]) == (
            env_successes.mean(),
            goals.mean(),
        )
    mixed = 0
    for (_, kwargs, (episodes, successes, _, _)), (args, _, sampled), ((trained, held, own_held), _, _) in zip(
        drawing, sampled_sets.calls, idm_trainings.calls[1:], strict=True
    ):
        _, successful, _, size, _ = args
        expected = Transitions.concat([e for e, ok in zip(episodes, successes, strict=True) if ok] or [pre.take([])])
        # only runs that reached the goal, less a tenth held out before I^s draws copies of them
        new_held = held.take(np.arange(len(pre_held), len(held)))
        assert np.array_equal(held.states[: len(pre_held)], pre_held.states)
        assert sorted_rows(own_held) == sorted_rows(new_held)  # a linear part's gate: the policy's own rollouts only
        assert sorted_rows(Transitions.concat([successful, new_held])) == sorted_rows(expected)
        assert len(new_held) <= len(held_out_split(len(expected), np.random.default_rng(0))[1])
        assert set(successful.actions.tolist()) == set(expected.actions.tolist())  # no action class held out whole
        assert trained is sampled  # the IDM trains on I^s and is scored on what I^s was not drawn from
        assert size == len(pre) and len(sampled) == len(pre)
        assert kwargs["explore"] is True
        mixed += 0 < successes.sum() < len(successes)
    assert mixed, "no cycle had both successful and failed rollouts: the test would not tell them apart"
    assert all(c["label_non_map"] > 0 for c in policy.cycles)  # labels are draws, not the IDM's argmax
    # rollouts play the expert dataset's own layouts
    played = {env.unwrapped.layout.layout_id for env in policy.trainer.rollouts.envs}
    assert played <= set(read_iupe_meta(maze_expert)["layout_ids"])
    # rollouts act by sampling: some actions are not the policy's argmax
    episodes = drawing[-1][2][0]
    states = torch.as_tensor(np.concatenate([e.states for e in episodes]))
    actions = np.concatenate([e.actions for e in episodes])
    assert (policy.pm_output(states).argmax(-1).numpy() != actions).any()
    # the checkpoint holds the model of the last selected cycle; the latest weights are kept beside it
    policy.save_pretrained(tmp_path / "ckpt")
    saved = load_file(tmp_path / "ckpt" / "model.safetensors")
    assert all(torch.equal(saved[k], v) for k, v in selected_pm.items())
    latest = torch.load(tmp_path / "ckpt" / TRAINING_STATE_FILE, weights_only=True)["latest_weights"]
    assert all(torch.equal(latest[k], v) for k, v in policy.state_dict().items())


def test_a_supervised_run_with_selection_episodes_keeps_its_best_step(
    cartpole_labelled, cartpole_random, monkeypatch, tmp_path
):
    """BC selects as BCO(α) and IUPE do: every cycle_steps steps it plays its selection episodes by the mode, from
    the same seeds, and its checkpoint is the best step's weights, not the last one's; no IDM cycle runs."""
    policy = build(cartpole_labelled, cartpole_random, supervised=True, selection_episodes=2)
    assert policy.config.separate_selection_episodes == 2
    rollouts = Spy(policy.trainer.rollout)
    monkeypatch.setattr(policy.trainer, "rollout", rollouts)
    monkeypatch.setattr(policy.trainer, "train_idm", Spy(policy.trainer.train_idm))
    optimizer = train_steps(policy, cartpole_labelled, 4)  # two cycles, real episodes
    assert [(c[0], c[1]["explore"]) for c in rollouts.calls] == [((2, rollouts.calls[0][0][1]), False)] * 2
    for cycle, (_, _, (_, goals, _, env_successes)) in zip(policy.cycles, rollouts.calls, strict=True):
        assert (cycle["selection_env_success_rate"], cycle["selection_goal_rate"]) == (
            env_successes.mean(),
            goals.mean(),
        )
    assert policy.trainer.state.pre is None and not policy.trainer.train_idm.calls  # no pre-demos, no IDM cycle
    # a scripted outcome for the next cycles: the best is the middle one
    rates = iter([{"env": 2.0, "goal": 2.0}, {"env": 0.0, "goal": 0.0}])
    monkeypatch.setattr(policy.trainer, "selection_rates", lambda episodes: next(rates))
    optimizer = train_steps(policy, cartpole_labelled, 2, optimizer)
    best = {k: v.clone() for k, v in policy.state_dict().items()}
    train_steps(policy, cartpole_labelled, 2, optimizer)
    assert [c["selected"] for c in policy.cycles[2:]] == [True, False]
    policy.save_pretrained(tmp_path / "ckpt")
    saved, latest = load_file(tmp_path / "ckpt" / "model.safetensors"), policy.state_dict()
    assert all(torch.equal(saved[k], v) for k, v in best.items() if not k.startswith("idm_"))
    assert any(not torch.equal(best[k], v) for k, v in latest.items() if k.startswith("pm_"))  # the last step differs
    # the IDM (trained on the same true actions; what relabelling reads) is the latest, not the selected step's
    assert all(torch.equal(saved[k], v) for k, v in latest.items() if k.startswith("idm_"))
    assert any(not torch.equal(best[k], v) for k, v in latest.items() if k.startswith("idm_"))


def test_a_supervised_run_cannot_select_without_an_env(cartpole_labelled, cartpole_random, tmp_path):
    copy = tmp_path / "no-env"
    shutil.copytree(cartpole_labelled, copy)
    (copy / "meta" / "iupe.json").unlink()
    files = {p: p.stat().st_mtime_ns for p in copy.rglob("*")}
    with pytest.raises(ValueError, match=r"--policy.selection_episodes=2 .* pass --env.type=<its env>"):
        build(copy, cartpole_random, supervised=True, selection_episodes=2)
    assert build(copy, cartpole_random, supervised=True).config.separate_selection_episodes == 0  # BC needs no env
    assert {p: p.stat().st_mtime_ns for p in copy.rglob("*")} == files  # the dataset is left as it was


def test_idm_only_trains_the_idm_alone_and_its_checkpoint_refuses_to_act(cartpole_labelled, cartpole_random):
    policy = build(cartpole_labelled, cartpole_random, supervised=True, idm_only=True)
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    policy.train()
    loss, logged = policy.forward(frame_batch(cartpole_labelled, 16))
    loss.backward()
    assert set(logged) == {"idm_loss"}
    assert all(p.grad is None for name, p in policy.named_parameters() if name.startswith("pm_"))
    assert non_policy_gradients(policy) == []  # every gradient is the optimizer's: the IDM's
    train_steps(policy, cartpole_labelled, 3)
    after = policy.state_dict()
    assert all(torch.equal(v, after[k]) for k, v in before.items() if k.startswith("pm_"))
    assert any(not torch.equal(v, after[k]) for k, v in before.items() if k.startswith("idm_"))
    with pytest.raises(ValueError, match=r"--policy.idm_only=true.*lerobot-iupe-relabel"):
        policy.select_action({"observation.state": torch.zeros(1, 4)})
    for wrong in ({}, {"selection_episodes": 2}):  # the IUPE cycle's, or a selection that plays the policy model
        with pytest.raises(ValueError, match=r"--policy.idm_only=true .* --policy.supervised=true"):
            IUPEConfig(idm_only=True, supervised=bool(wrong), **wrong)


def test_rollouts_play_only_the_last_rollout_layouts_of_the_expert_dataset(maze_expert, maze_random, monkeypatch):
    demonstrated = list(dict.fromkeys(read_iupe_meta(maze_expert)["layout_ids"]))
    policy = build(maze_expert, maze_random, rollout_layouts=2)
    played = []
    monkeypatch.setattr(rollouts, "run_episodes", Spy(rollouts.run_episodes))
    train_steps(policy, maze_expert, 4)  # two cycles of 4 rollouts and 4 selection episodes
    for (_, _, _, options), _, _ in rollouts.run_episodes.calls:
        played += [option["layout_id"] for option in options]
    assert len(demonstrated) > 2 and len(played) == 16
    assert set(played) == set(demonstrated[-2:])  # the selection never plays the other demonstrated layouts
    too_many = build(maze_expert, maze_random, rollout_layouts=len(demonstrated))
    with pytest.raises(ValueError, match=f"--policy.rollout_layouts={len(demonstrated)} must be below"):
        too_many.forward(frame_batch(maze_expert, 4))


def test_without_exploration_labels_and_rollouts_take_the_argmax(maze_expert, maze_random, monkeypatch):
    policy = build(maze_expert, maze_random, exploration=False)
    rollouts = Spy(policy.trainer.rollout)
    monkeypatch.setattr(policy.trainer, "rollout", rollouts)
    train_steps(policy, maze_expert, 2)
    assert policy.cycles[0]["label_non_map"] == 0
    episodes = rollouts.calls[0][2][0]
    states = torch.as_tensor(np.concatenate([e.states for e in episodes]))
    actions = np.concatenate([e.actions for e in episodes])
    assert (policy.pm_output(states).argmax(-1).numpy() == actions).all()


def test_rollout_records_state_action_and_next_state_of_the_same_step(cartpole_expert, cartpole_random):
    policy = build(cartpole_expert, cartpole_random)
    policy.forward(frame_batch(cartpole_expert, 16))
    episodes, successes, returns, _ = policy.trainer.rollout(3, seed=4242, explore=True)
    env = policy.trainer.rollouts.env_cfg.make()
    for i, episode in enumerate(episodes):
        observation, _ = env.reset(seed=4242 + i)
        total = 0.0
        for t, action in enumerate(episode.actions):
            assert np.array_equal(episode.states[t], observation["agent_pos"])
            observation, reward, *_ = env.step(int(action))
            assert np.array_equal(episode.next_states[t], observation["agent_pos"])
            total += reward
        assert total == returns[i]


@pytest.mark.parametrize("part", ["pm_encoder", "idm_encoder"])
def test_attention_gates_move_off_zero_in_training(cartpole_run, part):
    weights = load_file(cartpole_run / CHECKPOINT / "model.safetensors")
    assert weights[f"{part}.attention.gamma"].abs().item() > 0
