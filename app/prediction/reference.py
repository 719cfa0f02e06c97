"""NumPy references of the prediction package's compiled loops, for the tests and benchmarks only (nothing
at run time imports this module; ``tests/unit/test_layout.py`` checks that).

:func:`cap_speed_reference` is :func:`app.prediction._kernels.cap_speed` (the speed cap of every forecast,
:meth:`app.prediction.predictor.MotionPredictor._cap_speed`) over whole arrays.
:class:`ReferenceForecastArbiter` is :class:`app.prediction.arbitration.ForecastArbiter` scoring and taking
its quantiles in NumPy (:mod:`app.prediction._aci_kernels` compiled).
"""

from __future__ import annotations

import numpy as np

from app.prediction.arbitration import ForecastArbiter, _Ledger

__all__ = ["ReferenceForecastArbiter", "cap_speed_reference"]


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


class ReferenceForecastArbiter(ForecastArbiter):
    """:class:`ForecastArbiter` with its scoring and its per-step quantiles in NumPy (sorting every step's
    errors every frame): the reference of :func:`app.prediction._aci_kernels.score_due` and
    :func:`app.prediction._aci_kernels.step_quantiles`."""

    def _score_due(
        self, slots: np.ndarray, ks: np.ndarray, joints: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        assert self._futures is not None and self._combined is not None
        cand = np.linalg.norm(self._futures[slots, :, ks] - joints, axis=-1).mean(axis=-1)  # (V, C)
        per_joint = np.linalg.norm(self._combined[slots, ks] - joints, axis=-1)  # (V, J)
        miss = np.mean(per_joint > self._margins_at[slots, ks][:, None], axis=1)
        return cand, per_joint, miss

    def _quantiles(self, ledger: _Ledger) -> np.ndarray:
        """Per point of ``ledger`` the ``1 - alpha_t`` quantile of its recent joint errors, in NumPy."""
        assert ledger.err is not None
        n, W, J = ledger.err.shape
        m = ledger.count * J  # valid errors per point: the first ``count`` rows of the ring
        flat = np.where(np.arange(W * J)[None] < m[:, None], ledger.err.reshape(n, W * J), np.inf)
        flat.sort(axis=1)
        pos = np.clip(1.0 - ledger.alpha_t, 0.0, 1.0) * np.maximum(m - 1, 0)
        lo = np.floor(pos).astype(np.int64)
        hi = np.minimum(lo + 1, np.maximum(m - 1, 0))
        rows = np.arange(n)
        w = pos - lo
        return flat[rows, lo] * (1.0 - w) + np.where(w > 0, flat[rows, hi], 0.0) * w
