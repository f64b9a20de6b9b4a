"""The one compatibility check (data.compat) on real env configs and a real collected dataset."""

import pytest
from lerobot.datasets import LeRobotDatasetMetadata

from lerobot_iupe.data.compat import DataSpec, check_compatible, dataset_spec, env_spec
from lerobot_iupe.envs import AcrobotEnvConfig, CartPoleEnvConfig, MazeEnvConfig


def test_a_dataset_matches_the_env_it_was_collected_in(cartpole_expert):
    meta = LeRobotDatasetMetadata("local/cartpole-expert", root=cartpole_expert)
    spec = dataset_spec(meta, "observation.state", "the dataset")
    assert (spec.observation_shape, spec.fps, spec.env_type, spec.n_actions) == ((4,), 50, "cartpole", 2)
    check_compatible(env_spec(CartPoleEnvConfig(), "observation.state"), spec)
    with pytest.raises(ValueError, match=r"has shape \(4,\) in the dataset but \(6,\) in env acrobot"):
        check_compatible(env_spec(AcrobotEnvConfig(), "observation.state"), spec)


def test_every_disagreement_names_both_sides():
    env = env_spec(MazeEnvConfig(size=3, image_size=21), "observation.image")
    assert env.observation_shape == (21, 21, 3)  # as LeRobot stores images
    with pytest.raises(ValueError, match="reads 'observation.image' but the data has no such observation"):
        check_compatible(env, DataSpec("the data", "observation.image", available=("observation.state",)))
    for field, value, label in [("fps", 30, "fps"), ("env_type", "cartpole", "env type"), ("n_actions", 2, "number")]:
        other = DataSpec("the data", "observation.image", (21, 21, 3), **{field: value})
        with pytest.raises(ValueError, match=f"the data and env maze disagree on the {label}"):
            check_compatible(env, other)
    check_compatible(env, DataSpec("the data", "observation.image", (21, 21, 3)))  # unknown fields are not checked
