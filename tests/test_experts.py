import numpy as np
import pytest

from lerobot_iupe.envs import AcrobotEnvConfig, CartPoleEnvConfig, MazeEnvConfig, MountainCarEnvConfig
from lerobot_iupe.experts import make_agent, reference_returns


@pytest.mark.parametrize(
    ("cfg", "episodes", "minimum"),
    [
        (CartPoleEnvConfig(), 20, 499.0),
        (MountainCarEnvConfig(), 50, -100.0),
        (AcrobotEnvConfig(), 100, -76.0),
        (MazeEnvConfig(size=5), 50, 0.9),
    ],
    ids=["cartpole", "mountaincar", "acrobot", "maze5"],
)
def test_expert_meets_reference(cfg, episodes, minimum):
    expert = reference_returns(cfg, "expert", episodes)
    random = reference_returns(cfg, "random", 10)
    assert expert.mean() >= minimum
    assert expert.mean() > random.mean()


def test_reference_returns_are_seeded():
    cfg = CartPoleEnvConfig()
    assert np.array_equal(reference_returns(cfg, "random", 5, seed=3), reference_returns(cfg, "random", 5, seed=3))


def test_unknown_agent_is_refused():
    with pytest.raises(ValueError, match="--agent must be one of"):
        make_agent("cartpole", "oracle")
