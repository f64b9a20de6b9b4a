"""Labels a chunked policy can learn from (``relabel.consistency``, ``--pull_to_observation``).

A chunked policy (ACT, Diffusion) learns from one observation the next actions of the recording; an IDM error that
drifts with the state over a chunk is, to it, the expert's intent. The recording below is shaped like that: the
expert's action is a smooth function of the observation and the labels carry a drifting error, as an IDM's do
where the transition cannot tell the action (lag-1 autocorrelation 0.81–0.82 on LunarLander's engines)."""

import numpy as np

from lerobot_iupe.relabel.consistency import pull_toward_observation

CHUNK = 10
SPREAD = 0.1  # the IDM's std, in units of the action range


def drifting_recording(episodes: int = 30, frames: int = 100, seed: int = 0):
    """Observations (a random walk), the expert's smooth actions f(observation), labels = actions + an error that
    drifts (AR(1), 0.95 a frame), and each frame's episode."""
    rng = np.random.default_rng(seed)
    observations, actions, labels, episode = [], [], [], []
    for index in range(episodes):
        x = np.cumsum(rng.normal(0, 0.1, (frames, 3)), axis=0) + rng.normal(0, 1, 3)
        a = np.tanh(x @ np.array([[0.8, -0.3], [0.2, 0.6], [-0.5, 0.4]]))
        drift = np.zeros((frames, 2))
        for t in range(1, frames):
            drift[t] = 0.95 * drift[t - 1] + rng.normal(0, 0.05, 2)
        observations.append(x)
        actions.append(a)
        labels.append(np.clip(a + drift, -1, 1))
        episode.append(np.full(frames, index))
    return (np.concatenate(observations).astype(np.float32), np.concatenate(actions).astype(np.float32),
            np.concatenate(labels).astype(np.float32), np.concatenate(episode))  # fmt: skip


def chunk_offsets(labels: np.ndarray, actions: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """The labels' error averaged over every chunk of ``CHUNK`` frames within an episode: what a chunk of labels
    tells a policy beyond the expert's actions."""
    error = labels - actions
    starts = [t for t in range(len(error) - CHUNK) if episode[t] == episode[t + CHUNK]]
    return np.array([error[t : t + CHUNK].mean(axis=0) for t in starts])


def pulled(labels, observations, strength=1.0, seed=0, fixed_dims=None):
    spread = np.full_like(labels, SPREAD)
    low, high = np.full(2, -1.0), np.full(2, 1.0)
    return pull_toward_observation(labels, spread, observations, low, high, strength, seed, fixed_dims, steps=1500)


def test_pulled_labels_carry_less_of_the_drift_into_a_chunk():
    observations, actions, labels, episode = drifting_recording()
    rms = lambda x: float(np.sqrt(np.mean(np.square(x))))  # noqa: E731
    before = rms(chunk_offsets(labels, actions, episode))
    after = rms(chunk_offsets(pulled(labels, observations), actions, episode))
    # The labels as given carry an offset of 0.139 (rms) per chunk here; pulled by one std, 0.109.
    assert before > 0.1 and after < 0.85 * before, (before, after)


def test_a_label_moves_by_at_most_its_strength_in_stds_and_a_fixed_dimension_not_at_all():
    observations, _, labels, _ = drifting_recording(episodes=10)
    moved = pulled(labels, observations, strength=0.5, fixed_dims=np.array([False, True]))
    # strength × std × range (2): 0.1 of the action's units here
    assert np.abs(moved - labels)[:, 0].max() <= 0.5 * SPREAD * 2 + 1e-6
    assert np.abs(moved - labels)[:, 0].max() > 0.05
    np.testing.assert_array_equal(moved[:, 1], labels[:, 1])


def test_strength_0_keeps_the_idms_labels_and_a_seed_gives_the_same_labels():
    observations, _, labels, _ = drifting_recording(episodes=5)
    np.testing.assert_array_equal(pulled(labels, observations, strength=0.0), labels)
    np.testing.assert_array_equal(pulled(labels, observations, seed=3), pulled(labels, observations, seed=3))


def test_a_pull_never_moves_a_label_outside_the_action_bounds():
    rng = np.random.default_rng(0)
    observations = rng.normal(size=(400, 3)).astype(np.float32)
    # Labels at the bounds whose regression on the observation reaches beyond them, with a wide IDM std.
    labels = np.clip(3.0 * observations[:, :2], -1.0, 1.0).astype(np.float32)
    spread = np.full_like(labels, 0.5)
    pulled = pull_toward_observation(labels, spread, observations, np.array([-1.0, -1.0]), np.array([1.0, 1.0]),
                                     1.0, seed=0, steps=300)  # fmt: skip
    assert (pulled >= -1.0).all() and (pulled <= 1.0).all()
    assert not np.allclose(pulled, labels)  # the pull did move them
