"""The policy model's weight average (``--policy.ema_decay``): its rule, what acts and what is saved."""

import pytest
import torch
from conftest import CHECKPOINT, run_in_process
from safetensors.torch import load_file
from test_modeling import make_policy

from lerobot_iupe.policy import IUPEConfig, IUPEPolicy


def pm_weights(policy: IUPEPolicy) -> dict[str, torch.Tensor]:
    return {n: p.detach().clone() for n, p in policy.named_parameters() if n.startswith("pm_")}


def set_weights(policy: IUPEPolicy, value: float) -> None:
    with torch.no_grad():
        for parameter in policy.parameters():
            parameter.fill_(value)


def test_the_average_follows_its_rule_acts_inside_its_block_and_is_what_is_saved(tmp_path):
    policy = make_policy(image=False, ema_decay=0.75)
    set_weights(policy, 2.0)
    policy.update()  # the first step starts the average at the weights
    set_weights(policy, 6.0)
    policy.update()  # 0.75 · 2 + 0.25 · 6
    assert all(torch.equal(a, torch.full_like(a, 3.0)) for a in policy.averaged.values())
    assert set(policy.averaged) == set(pm_weights(policy))  # the policy model only: the IDM is not averaged
    with policy.averaged_weights():
        assert all(torch.equal(w, torch.full_like(w, 3.0)) for w in pm_weights(policy).values())
        idm = [p for n, p in policy.named_parameters() if n.startswith("idm_")]
        assert all(torch.equal(p, torch.full_like(p, 6.0)) for p in idm)
    assert all(torch.equal(w, torch.full_like(w, 6.0)) for w in pm_weights(policy).values())  # trained ones back
    policy.save_pretrained(tmp_path)
    saved = load_file(tmp_path / "model.safetensors")
    assert all(torch.equal(saved[n], torch.full_like(saved[n], 3.0)) for n in pm_weights(policy))
    assert all(torch.equal(v, torch.full_like(v, 6.0)) for n, v in saved.items() if n.startswith("idm_"))
    assert all(torch.equal(w, torch.full_like(w, 6.0)) for w in pm_weights(policy).values())


def test_without_a_decay_there_is_no_average_and_the_weights_are_saved(tmp_path):
    policy = make_policy(image=False)
    set_weights(policy, 2.0)
    policy.update()
    assert policy.averaged is None
    with policy.averaged_weights():
        assert all(torch.equal(w, torch.full_like(w, 2.0)) for w in pm_weights(policy).values())
    policy.save_pretrained(tmp_path)
    saved = load_file(tmp_path / "model.safetensors")
    assert all(torch.equal(saved[n], torch.full_like(p, 2.0)) for n, p in policy.named_parameters())


@pytest.mark.parametrize("decay", [1.0, -0.1])
def test_a_decay_outside_zero_to_one_is_refused_naming_the_flag(decay):
    with pytest.raises(ValueError, match=r"--policy.ema_decay must be in \[0, 1\)"):
        IUPEConfig(ema_decay=decay)


def test_lerobot_train_saves_the_average_and_trains_the_same_weights(cartpole_labelled, tmp_path):
    """BC with and without the average, same seed: the IDM (trained, never averaged) comes out identical, the
    policy model's saved weights differ (the average of the same trajectory)."""
    saved = {}
    for decay in ("0", "0.9"):
        out = tmp_path / decay
        run_in_process(
            "lerobot-train", "--policy.type=iupe", "--policy.supervised=true",
            f"--dataset.repo_id=local/{cartpole_labelled.name}", f"--dataset.root={cartpole_labelled}",
            f"--output_dir={out}", "--num_workers=0", "--policy.device=cpu", "--wandb.enable=false", "--steps=30",
            "--save_freq=30", "--batch_size=32", "--seed=3", f"--policy.ema_decay={decay}", check=True
        )  # fmt: skip
        saved[decay] = load_file(out / CHECKPOINT / "model.safetensors")
    plain, averaged = saved["0"], saved["0.9"]
    assert all(torch.equal(v, averaged[n]) for n, v in plain.items() if n.startswith("idm_"))
    pm = [n for n in plain if n.startswith("pm_") and "gamma" not in n]
    assert pm and all(not torch.equal(plain[n], averaged[n]) for n in pm)
