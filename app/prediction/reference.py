"""NumPy references of the prediction package's compiled loops, for the tests and benchmarks only (nothing
at run time imports this module; ``tests/unit/test_layout.py`` checks that).

:func:`cap_speed_reference` is :func:`app.prediction._kernels.cap_speed` (the speed cap of every forecast,
:meth:`app.prediction.predictor.MotionPredictor._cap_speed`) over whole arrays.
"""

from __future__ import annotations

import numpy as np

__all__ = ["cap_speed_reference"]


def cap_speed_reference(
    last: np.ndarray, future: np.ndarray, *, dt_s: float, max_speed_mps: float
) -> np.ndarray:
    """The forecast's joints (H + 1, J, 3): ``last`` (J, 3), then ``future`` (H, J, 3) with every joint's
    displacement from ``last`` capped at ``max_speed_mps`` times the step's time ``dt_s * (h + 1)`` (m)."""
    t = dt_s * np.arange(1, future.shape[0] + 1)[:, None, None]
    disp = future - last[None]
    dist = np.linalg.norm(disp, axis=-1, keepdims=True)
    limit = max_speed_mps * t
    scale = np.where(dist > limit, limit / np.maximum(dist, 1e-12), 1.0)
    return np.concatenate([last[None], last[None] + disp * scale], axis=0)
