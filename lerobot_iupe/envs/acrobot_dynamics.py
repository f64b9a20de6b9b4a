"""A batched numpy copy of gymnasium's Acrobot-v1 dynamics (one RK4 step of 0.2 s, "book" equations).

Used to search the built-in expert's weights and by the lookahead planner; it matches gymnasium's step for
states of any leading shape ``(..., 4)`` = (θ1, θ2, θ̇1, θ̇2)."""

from __future__ import annotations

import numpy as np

DT = 0.2


def derivatives(s: np.ndarray, torque: np.ndarray) -> np.ndarray:
    m1 = m2 = 1.0
    l1, lc1, lc2, i1, i2, g = 1.0, 0.5, 0.5, 1.0, 1.0, 9.8
    t1, t2, dt1, dt2 = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    d1 = m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * np.cos(t2)) + i1 + i2
    d2 = m2 * (lc2**2 + l1 * lc2 * np.cos(t2)) + i2
    phi2 = m2 * lc2 * g * np.cos(t1 + t2 - np.pi / 2.0)
    phi1 = (
        -m2 * l1 * lc2 * dt2**2 * np.sin(t2)
        - 2 * m2 * l1 * lc2 * dt2 * dt1 * np.sin(t2)
        + (m1 * lc1 + m2 * l1) * g * np.cos(t1 - np.pi / 2)
        + phi2
    )
    ddt2 = (torque + d2 / d1 * phi1 - m2 * l1 * lc2 * dt1**2 * np.sin(t2) - phi2) / (m2 * lc2**2 + i2 - d2**2 / d1)
    ddt1 = -(d2 * ddt2 + phi1) / d1
    return np.stack([dt1, dt2, ddt1, ddt2], axis=-1)


def step(s: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """Next state after applying ``torque`` (−1, 0 or +1) for one 0.2 s step."""
    k1 = derivatives(s, torque)
    k2 = derivatives(s + DT / 2 * k1, torque)
    k3 = derivatives(s + DT / 2 * k2, torque)
    k4 = derivatives(s + DT * k3, torque)
    ns = s + DT / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    ns[..., 0] = (ns[..., 0] + np.pi) % (2 * np.pi) - np.pi
    ns[..., 1] = (ns[..., 1] + np.pi) % (2 * np.pi) - np.pi
    ns[..., 2] = np.clip(ns[..., 2], -4 * np.pi, 4 * np.pi)
    ns[..., 3] = np.clip(ns[..., 3], -9 * np.pi, 9 * np.pi)
    return ns


def tip_height(s: np.ndarray) -> np.ndarray:
    """Height of the tip above the pivot; the goal is reached when it exceeds 1."""
    return -np.cos(s[..., 0]) - np.cos(s[..., 1] + s[..., 0])


def observation(s: np.ndarray) -> np.ndarray:
    t1, t2 = s[..., 0], s[..., 1]
    return np.stack([np.cos(t1), np.sin(t1), np.cos(t2), np.sin(t2), s[..., 2], s[..., 3]], axis=-1)
