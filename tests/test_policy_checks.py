"""LeRobot's own three checks of every policy (its tests/policies/test_policies.py), held to both of ours: the
config annotation is the config class, the policy builds with defaults from features alone (LeRobot's dummy
features, as its Python training example builds one), and save/load round-trips every parameter exactly."""

import inspect

import pytest
import torch
from lerobot.configs import FeatureType, PolicyFeature, PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_policy_config

import lerobot_iupe  # noqa: F401  (registers the policy types)

POLICIES = ["iupe", "ilpo"]
DUMMY_INPUTS = {
    "observation.images.laptop": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 84, 84)),
    "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(6,)),
}
DUMMY_ACTION = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(6,))}


def built(name: str):
    config = make_policy_config(name, device="cpu")
    config.input_features, config.output_features = dict(DUMMY_INPUTS), dict(DUMMY_ACTION)
    return get_policy_class(name)(config)


@pytest.mark.parametrize("name", POLICIES)
def test_the_policy_annotates_its_config_with_the_config_class(name):
    annotation = inspect.signature(get_policy_class(name).__init__).parameters["config"].annotation
    assert inspect.isclass(annotation) and issubclass(annotation, PreTrainedConfig)
    assert annotation is PreTrainedConfig.get_choice_class(name)


@pytest.mark.parametrize("name", POLICIES)
def test_the_policy_builds_from_features_alone_and_acts(name):
    policy = built(name)
    batch = {"observation.images.laptop": torch.rand(2, 3, 84, 84), "observation.state": torch.randn(2, 6)}
    action = policy.select_action(batch)
    assert action.shape == (2, 6)
    assert (action >= -1).all() and (action <= 1).all()  # no env, no data: a box of [-1, 1] per dimension


@pytest.mark.parametrize("name", POLICIES)
def test_save_and_load_round_trip_every_parameter_exactly(name, tmp_path):
    torch.manual_seed(0)
    policy = built(name)
    policy.save_pretrained(tmp_path)
    loaded = get_policy_class(name).from_pretrained(tmp_path)
    saved, restored = policy.state_dict(), loaded.state_dict()
    assert saved.keys() == restored.keys()
    assert all(torch.equal(saved[k], restored[k]) for k in saved)
