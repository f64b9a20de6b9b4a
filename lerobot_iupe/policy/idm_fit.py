"""One IDM fit of the cycle: epochs over I^s, then its score on held-out transitions."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from lerobot_iupe.data.transitions import Transitions
from lerobot_iupe.policy.algorithm import r_squared
from lerobot_iupe.policy.linear_prior import judge_gate


def fit_idm(
    policy: nn.Module,
    optimizer: torch.optim.Optimizer,
    data: Transitions,
    held_out: Transitions,
    rng: np.random.Generator,
    own_held_out: Transitions | None = None,
) -> tuple[float, float]:
    """Train ``policy``'s IDM (an ``IUPEPolicy``'s) on all of ``data`` for ``idm_epochs`` shuffled epochs of
    ``idm_batch_size``, then score it on ``held_out``, transitions of which ``data`` holds no copy: label agreement
    (discrete actions) or R² (continuous). With a linear part, the network's share is judged on ``own_held_out``
    alone (the policy's own held-out rollout transitions; none: the linear part labels alone, ``judge_gate``).
    Returns (the last batch's loss, the score; NaN with nothing held out)."""
    config, device = policy.config, policy.device_of_weights
    train = rng.permutation(len(data))
    to = lambda x: torch.as_tensor(x, device=device)  # noqa: E731
    if policy.idm_prior is not None:  # the linear part first, in closed form; the network learns what it leaves
        policy.fit_prior(policy.idm_prior.features(data.windows), data.actions, fixed=True)
    policy.train()
    for _ in range(config.idm_epochs):
        rng.shuffle(train)
        for start in range(0, len(train), config.idm_batch_size):
            idx = train[start : start + config.idm_batch_size]
            output = policy.idm_window_output(to(data.windows[idx]))
            loss = policy.idm_head.loss(output, to(data.actions[idx]))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    # lerobot-train clips (and logs) the norm of every parameter's gradient: only the policy model's may be left.
    optimizer.zero_grad(set_to_none=True)
    if policy.idm_prior is not None and policy.idm_prior.is_fitted:
        judge_gate(policy, own_held_out)
    policy.eval()
    with torch.no_grad():
        predicted = []
        for start in range(0, len(held_out), 1024):
            part = held_out.take(np.arange(start, min(start + 1024, len(held_out))))
            output = policy.idm_window_output(to(part.windows))
            predicted.append(policy.idm_head.mode(output).cpu().numpy())
    policy.train()
    if not predicted:  # a single pre-demonstration transition: nothing to hold out
        return float(loss.detach()), float("nan")
    predicted, true = np.concatenate(predicted), held_out.actions
    score = r_squared(predicted, true) if config.is_continuous else float((predicted == true).mean())
    return float(loss.detach()), score
