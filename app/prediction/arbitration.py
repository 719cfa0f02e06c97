"""Online arbitration between forecasts, and adaptive conformal margins.

A network that forecasts some people brilliantly can forecast others (motion unlike its training data) far
worse than holding the pose still. At run time nobody knows in advance which case the cell is in, but the
past tells: every forecast made ``h`` seconds ago can be scored against the frame that has just arrived.
:class:`ForecastArbiter` keeps, per candidate (the network, constant velocity, zero velocity, ...) and per
horizon step, the mean joint error of its recent forecasts over a sliding window, and hands on, per horizon
step, the candidate whose recent error is lowest. Until a candidate has been scored ``min_scores`` times at
a step, the first candidate in the order given (the network) is taken.

The margins come from adaptive conformal inference (ACI; Gibbs and Candès, "Adaptive conformal inference
under distribution shift", NeurIPS 2021): per horizon step the margin is the ``1 - alpha_t`` quantile of the
recent joint errors of the arbitrated forecast, and after every scored forecast ``alpha_t`` moves by
``gamma * (alpha - miss)``, where ``miss`` is the fraction of joints that fell outside the margin. The
margins widen on motion the forecast gets wrong and shrink on motion it gets right, and the fraction of
joints inside them tracks the target coverage ``1 - alpha`` (default 95 %) over time, whatever the motion.

Pure computation over numpy arrays; cheap enough to run at the camera rate beside the planner (a few
hundred small array operations per frame).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["ArbitratedForecast", "ForecastArbiter"]


@dataclass(frozen=True, slots=True)
class ArbitratedForecast:
    """The forecast handed on.

    Attributes:
        joints: (H + 1, J, 3) poses at the horizon steps (step 0: the newest frame).
        margins: (H + 1,) margin (m) per step: the adaptive conformal quantile of recent joint errors.
        chosen: (H + 1,) the candidate taken at each step.
    """

    joints: np.ndarray
    margins: np.ndarray
    chosen: tuple[str, ...]


class ForecastArbiter:
    """Scores candidate forecasts against the frames that arrive and combines them (module docstring).

    Args:
        candidates: The candidates' names, the preferred one first.
        horizon: Forecast steps after the newest frame (H).
        dt_s: Time between steps (s): the frame period the forecasts are made at.
        window: Scored forecasts kept per candidate and step.
        min_scores: Scores needed at a step before a candidate can be chosen over the first.
        coverage: Target fraction of joints inside the margin (``1 - alpha``).
        gamma: ACI step size.
        floor_m: Smallest margin (m) (the tracker's noise).
        prior_m: Margin per step (H + 1,) until errors have been seen at that step (m).
    """

    def __init__(
        self,
        candidates: Sequence[str],
        *,
        horizon: int,
        dt_s: float,
        window: int = 90,
        min_scores: int = 10,
        coverage: float = 0.95,
        gamma: float = 0.005,
        floor_m: float = 0.02,
        prior_m: np.ndarray | None = None,
    ) -> None:
        if not candidates:
            raise ValueError("ForecastArbiter needs at least one candidate")
        if not (0.0 < coverage < 1.0):
            raise ValueError(f"coverage must be in (0, 1), got {coverage}")
        if horizon < 1 or not dt_s > 0:
            raise ValueError(f"horizon must be >= 1 and dt_s > 0, got {horizon}, {dt_s}")
        self.candidates = tuple(candidates)
        self.horizon = int(horizon)
        self.dt_s = float(dt_s)
        self.window = int(window)
        self.min_scores = int(min_scores)
        self.alpha = 1.0 - float(coverage)
        self.gamma = float(gamma)
        self.floor_m = float(floor_m)
        n = self.horizon + 1
        self.prior_m = (
            np.full(n, 0.1) if prior_m is None else np.asarray(prior_m, dtype=np.float64).reshape(n).copy()
        )
        self._errors = {c: [deque(maxlen=self.window) for _ in range(n)] for c in self.candidates}
        self._joint_errors: list[deque[np.ndarray]] = [deque(maxlen=self.window) for _ in range(n)]
        self._alpha_t = np.full(n, self.alpha)
        self._pending: deque[tuple[float, dict[str, np.ndarray], np.ndarray, np.ndarray]] = deque()
        self.covered = np.zeros(n)  # joints inside the margin, per step, since the start
        self.scored = np.zeros(n)  # joints scored, per step

    def reset(self) -> None:
        """Forget everything (a new person)."""
        self.__init__(  # type: ignore[misc]
            self.candidates,
            horizon=self.horizon,
            dt_s=self.dt_s,
            window=self.window,
            min_scores=self.min_scores,
            coverage=1.0 - self.alpha,
            gamma=self.gamma,
            floor_m=self.floor_m,
            prior_m=self.prior_m,
        )

    # ------------------------------------------------------------------------------------------------
    def score(self, t: float, joints: np.ndarray) -> None:
        """Score the stored forecasts against the frame ``joints`` (J, 3) seen at ``t`` (s)."""
        joints = np.asarray(joints, dtype=np.float64)
        while self._pending and t - self._pending[0][0] > (self.horizon + 0.5) * self.dt_s:
            self._pending.popleft()
        for t0, futures, combined, margins in self._pending:
            k = round((t - t0) / self.dt_s)
            if k < 1 or k > self.horizon or abs(t - t0 - k * self.dt_s) > 0.25 * self.dt_s:
                continue
            for name, future in futures.items():
                err = float(np.linalg.norm(future[k] - joints, axis=1).mean())
                self._errors[name][k].append(err)
            per_joint = np.linalg.norm(combined[k] - joints, axis=1)
            self._joint_errors[k].append(per_joint)
            miss = float(np.mean(per_joint > margins[k]))
            self.covered[k] += per_joint.size * (1.0 - miss)
            self.scored[k] += per_joint.size
            self._alpha_t[k] = min(max(self._alpha_t[k] + self.gamma * (self.alpha - miss), 0.0), 1.0)

    def combine(self, t0: float, futures: Mapping[str, np.ndarray]) -> ArbitratedForecast:
        """Combine the candidates' forecasts (each (H + 1, J, 3), step 0 the frame at ``t0``) by their recent
        errors, and remember them to be scored."""
        missing = [c for c in self.candidates if c not in futures]
        if missing:
            raise ValueError(f"ForecastArbiter.combine: no forecast from {missing}")
        n = self.horizon + 1
        first = self.candidates[0]
        chosen = [first] * n
        for k in range(1, n):
            best, best_err = first, math.inf
            for name in self.candidates:
                errs = self._errors[name][k]
                if len(errs) < self.min_scores:
                    continue
                e = float(np.mean(errs))
                if e < best_err - 1e-12:
                    best, best_err = name, e
            chosen[k] = best
        joints = np.stack([np.asarray(futures[chosen[k]][k], dtype=np.float64) for k in range(n)])
        margins = self.margins()
        stored = {c: np.asarray(futures[c], dtype=np.float64) for c in self.candidates}
        self._pending.append((float(t0), stored, joints, margins))
        return ArbitratedForecast(joints=joints, margins=margins, chosen=tuple(chosen))

    def margins(self) -> np.ndarray:
        """(H + 1,) the adaptive conformal margin (m) per step."""
        out = self.prior_m.copy()
        for k in range(1, self.horizon + 1):
            if len(self._joint_errors[k]) >= self.min_scores:
                errs = np.concatenate(list(self._joint_errors[k]))
                q = 1.0 - float(self._alpha_t[k])
                out[k] = float(np.max(errs)) if q >= 1.0 else float(np.quantile(errs, max(q, 0.0)))
        out[0] = min(out[0], self.floor_m) if self.horizon else out[0]
        return np.maximum(out, self.floor_m)

    def coverage(self) -> np.ndarray:
        """(H + 1,) fraction of joints that fell inside the margin, per step, since the start (NaN where none
        was scored)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.scored > 0, self.covered / np.maximum(self.scored, 1), np.nan)
