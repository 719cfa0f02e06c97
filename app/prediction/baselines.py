"""Baseline forecasts: zero velocity (hold the last pose) and constant velocity.

Both take uniformly sampled observed poses (P, T, J, 3) (world frame, metres, at ``fps``) and return the H
future poses (P, H, J, 3) at ``1/fps`` spacing after the last observed frame.
"""

from __future__ import annotations

import numpy as np


def _check(history: np.ndarray, horizon: int, name: str) -> np.ndarray:
    history = np.asarray(history, dtype=np.float64)
    if history.ndim != 4 or history.shape[-1] != 3 or history.shape[1] < 1:
        raise ValueError(f"{name} expects history of shape (P, T, J, 3) with T >= 1, got {history.shape}")
    if horizon < 1:
        raise ValueError(f"{name} needs horizon >= 1, got {horizon}")
    return history


def zero_velocity(history: np.ndarray, horizon: int) -> np.ndarray:
    """The last observed pose held for ``horizon`` frames: (P, T, J, 3) -> (P, H, J, 3)."""
    history = _check(history, horizon, "zero_velocity")
    return np.repeat(history[:, -1:], horizon, axis=1)


def constant_velocity(history: np.ndarray, horizon: int) -> np.ndarray:
    """Every joint keeps its last frame-to-frame velocity: (P, T, J, 3) -> (P, H, J, 3).

    With a single observed frame this is the zero-velocity forecast.
    """
    history = _check(history, horizon, "constant_velocity")
    if history.shape[1] < 2:
        return zero_velocity(history, horizon)
    step = history[:, -1] - history[:, -2]  # (P, J, 3) per frame
    k = np.arange(1, horizon + 1, dtype=np.float64)[None, :, None, None]
    return history[:, -1:] + k * step[:, None]


BASELINES = {"zero_velocity": zero_velocity, "constant_velocity": constant_velocity}
