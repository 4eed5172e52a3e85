"""Generalized advantage estimation for one episode, with time-limit truncation handled.

An episode of ``T`` steps carries ``T + 1`` value estimates: ``values[t]`` for the observation
before step ``t`` and ``values[T]`` for the observation after the last step. At the last step the
next value is ``values[T]`` when the episode was cut by the time limit (truncated: the state
was not terminal, so the return continues) and 0 when it terminated. An episode that is neither
(a segment cut by the collector) is bootstrapped like a truncation; one that is both counts as
terminated.

    delta_t = r_t + gamma * V_{t+1} - V_t      (V_T = 0 on termination)
    A_t     = delta_t + gamma * lambda * A_{t+1},     returns_t = A_t + V_t
"""

from __future__ import annotations

import numpy as np

__all__ = ["compute_gae"]


def compute_gae(
    rewards: np.ndarray,
    values: np.ndarray,
    terminated: bool,
    truncated: bool,
    gamma: float,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``(advantages (T,), returns (T,))`` as float32 for one episode (see module docs)."""
    r = np.asarray(rewards, dtype=np.float64).reshape(-1)
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.shape[0] != r.shape[0] + 1:
        raise ValueError(f"values must have len(rewards) + 1 = {r.shape[0] + 1} entries, got {v.shape[0]}")
    if not 0.0 <= gamma <= 1.0 or not 0.0 <= lam <= 1.0:
        raise ValueError(f"gamma and lam must lie in [0, 1], got gamma={gamma}, lam={lam}")
    next_values = v[1:].copy()
    if bool(terminated):
        next_values[-1:] = 0.0
    deltas = r + gamma * next_values - v[:-1]
    adv = np.empty_like(deltas)
    running = 0.0
    for t in range(deltas.shape[0] - 1, -1, -1):
        running = deltas[t] + gamma * lam * running
        adv[t] = running
    returns = adv + v[:-1]
    return adv.astype(np.float32), returns.astype(np.float32)
