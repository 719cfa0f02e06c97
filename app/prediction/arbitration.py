"""Online arbitration between forecasts, and adaptive conformal margins.

A network that forecasts some people brilliantly can forecast others (motion unlike its training data) far
worse than holding the pose still. At run time nobody knows in advance which case the cell is in, but the
past tells: every forecast made ``h`` seconds ago can be scored against the frame that has just arrived.
:class:`ForecastArbiter` keeps, per candidate (the network, constant velocity, zero velocity, ...) and per
horizon step, the mean joint error of its recent forecasts over a sliding window, and hands on, per horizon
step, the candidate whose recent error is lowest. Until the candidates have been scored ``min_scores`` times
at a step, the first candidate in the order given (the network) is taken there, unless another has been
clearly better at the longest step scored enough (``transfer_ratio``): a step ``k`` frames ahead is scored
only ``k`` frames after its forecast, so the far steps learn last.

The margins come from adaptive conformal inference (ACI; Gibbs and Candès, "Adaptive conformal inference
under distribution shift", NeurIPS 2021): per horizon step the margin is the ``1 - alpha_t`` quantile of the
recent joint errors of the arbitrated forecast, and after every scored forecast ``alpha_t`` moves by
``gamma * (alpha_k - miss)``, where ``miss`` is the fraction of joints that fell outside the margin and
``alpha_k`` the step's target miss rate: ``alpha`` at step 0, lower at the far steps, which are scored late
(:data:`FAR_ALPHA_FACTOR`). The margins widen on motion the forecast gets wrong and shrink on motion it
gets right, and the fraction of joints inside them tracks the step's target (``1 - alpha``, default 95 %,
at step 0) over time, whatever the motion. Halfway between each two steps, where the planner checks plans
too, the margins are calibrated the same way on the forecasts there (``half_steps``).
A new person starts from a prior, which stays a floor through the first ``warmup`` scores of a step: the
larger of a stored error quantile of the network on clips it was not trained on (:func:`prior_margins`) and
the person's *motion scale* ``s_k`` times a factor. ``s_k`` is what the candidates say of how far the person
may move by step ``k`` (the largest mean joint displacement any candidate forecasts, plus a floor), so the
prior of a person who moves fast is wide from the first frame, whatever the network was trained on. As the
near steps are scored, the factor becomes the quantile of their errors divided by the motion scale they were
forecast with (locally weighted conformal scores, Lei et al., "Distribution-free predictive inference for
regression", JASA 2018, section 5.2), carried to the far steps that are not scored yet.

Pure computation over numpy arrays; cheap enough to run at the camera rate beside the planner (a few
hundred small array operations per frame).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.prediction._aci_kernels import score_due, step_quantiles

log = logging.getLogger(__name__)

__all__ = ["ArbitratedForecast", "ForecastArbiter", "prior_margins"]


#: Default ``transfer_ratio``. Tuned (one value tried against 0) on the CMU train split (MPJPE unchanged,
#: 150.1 mm at 1 s) and on simulated operators with seeds 1000-1005, 60 s each (forecast MPJPE / best baseline
#: at 1 s: 1.066 with 0, 1.015 with 0.5): a new person whom the network forecasts badly no longer gets the
#: network's far steps until they are scored.
TRANSFER_RATIO = 0.5

#: The prior is the stored error quantile at ``1 - (1 - coverage) / COLD_START_MISS_FACTOR`` (p99 for a 95 %
#: target): a person never seen is forecast worse than the validation clips the quantiles come from. Tuned on
#: the CMU train split (shipped weights, every clip a new person; coverage at 80..1000 ms): factor 1 (p95)
#: 0.942..0.949, factor 5 (p99) 0.951..0.955.
COLD_START_MISS_FACTOR = 5.0

#: The ACI aims at the miss rate ``alpha`` at step 0, falling linearly to ``FAR_ALPHA_FACTOR * alpha`` at the
#: last step (97.5 % inside at 1 s for a 95 % target). A step ``k`` frames ahead is scored ``k`` frames late,
#: so its margin reacts to a change of motion (an operator who stood still walks off) only after the
#: forecasts made before it have missed: aiming the far steps a little higher makes up for the misses that
#: arrive before the level can move. Tuned with the motion-scaled prior, a 30-score warm-up and
#: ``MIN_SCORES``, taking the factor whose worst coverage deviation from 95 % over the three tuning sets is
#: smallest; coverage at 1 s with 0.3 | 0.4 | 0.5: network trained without CMU on the CMU train split
#: 0.952 | 0.949 | 0.945; network trained on every source on the CMU validation clips 0.971 | 0.968 | 0.963
#: and on simulated operators with seeds 1000-1009 0.944 | 0.940 | 0.936 (worst deviation 2.1 | 1.8 | 1.4
#: points). (Before the motion-scaled prior it was tuned the same way: sim 1.0 (none): 0.919 / 282 mm,
#: 0.5: 0.937 / 299 mm; there a longer window (300 scores: 0.931 at 1 s, 458 mm), a faster step (gamma
#: 0.01: 0.912) and errors scaled by the person's recent speed throughout (0.925 at 1 s with 337 mm) were
#: tried and dropped.)
FAR_ALPHA_FACTOR = 0.5

#: A new person's prior is at least ``COLD_START_SCALE`` times their motion scale (see the module docstring)
#: until the steps are scored, and the motion scale has a floor of ``MOTION_SCALE_FLOOR_M`` (a still
#: person's tracking noise and small motions). Tuned on the CMU train split with a network trained without any
#: CMU clip (``hrc hmp train --leave-out cmu``: every clip a new person of a kind the network never saw;
#: coverage at 1 s was 0.907, 0.72 in the first 60 forecasts of a clip; with 0, 1.5, 2 and 3, then still
#: with a 90-score warm-up and 10 scores per ready step: 0.935, 0.951, 0.957 and 0.967, mean margin at 1 s
#: 1.14, 1.13, 1.19 and 1.33 m) and checked on simulated operators with seeds 1000-1009. Tuned again the same
#: way after the warm-up, ``MIN_SCORES`` and the arbiter's start with the first full history had changed
#: what it floors (coverage at 1 s on that set with 2.0 | 2.5 | 3.0: 0.9454 | 0.9500 | 0.9535, at 80..1000 ms
#: 0.945..0.950 | 0.947..0.950 | 0.947..0.954; mean margin at 1 s 0.95 | 1.01 | 1.07 m; the CMU validation
#: clips with the network trained on every source 0.963 and the simulated operators 0.936 at 1 s with each).
#: The floor was set, not tuned: 0.02 m gave the same coverage on those operators.
COLD_START_SCALE = 2.5
MOTION_SCALE_FLOOR_M = 0.05

#: Scores at a step before another candidate may be taken there instead of the preferred one, and before the
#: margin there comes from the scores at all. A network that forecasts a new kind of person badly at the near
#: steps is used there until then. Tuned on the CMU train split with a network trained without CMU (forecast
#: MPJPE / best baseline at 80 ms: 10 scores 1.037, 5 1.000, 3 0.981; coverage unchanged within 0.1 points)
#: and checked on the CMU validation clips with the network trained on every source (1.018 at 80 ms with 5).
MIN_SCORES = 5

#: Scores at a step before the ACI quantile alone sets its margin (the prior a floor until then). With the
#: motion-scaled prior a new person no longer needs a whole window of it. Tuned on the CMU train split
#: (network trained without CMU; coverage at 80..1000 ms: warm-up 0 0.933..0.949, 30 0.946..0.950) and on the
#: validation clips (network trained on every source: warm-up 90 0.958..0.973, 30 0.950..0.964, 0
#: 0.948..0.961, mean margin at 1 s 983, 838 and 750 mm).
WARMUP = 30


@dataclass(frozen=True, slots=True)
class ArbitratedForecast:
    """The forecast handed on.

    Attributes:
        joints: (H + 1, J, 3) poses at the horizon steps (step 0: the newest frame).
        margins: (H + 1,) margin (m) per step: the adaptive conformal quantile of recent joint errors.
        chosen: (H + 1,) the candidate taken at each step.
        half_margins: (H,) margin (m) halfway between step ``k`` and ``k + 1``, calibrated there
            (:class:`ForecastArbiter`'s ``half_steps``), or None (then the steps' margins hold between them,
            linearly interpolated).
    """

    joints: np.ndarray
    margins: np.ndarray
    chosen: tuple[str, ...]
    half_margins: np.ndarray | None = None


class _Ledger:
    """The adaptive conformal bookkeeping of one set of horizon points (the steps, or the points halfway
    between them): per point a ring of the recent joint errors, the ACI level and its target miss rate, the
    quantiles found last time (a hint for the next) and the joints inside the margin so far."""

    def __init__(self, alpha_k: np.ndarray, window: int) -> None:
        n = alpha_k.shape[0]
        self.alpha_k = alpha_k
        self.window = window
        self.err: np.ndarray | None = None  # (n, W, J), allocated at the first score
        self.count = np.zeros(n, dtype=np.int64)
        self.head = np.zeros(n, dtype=np.int64)
        self.alpha_t = alpha_k.copy()
        self.q_last = np.full(n, np.inf)
        self.covered = np.zeros(n)
        self.scored = np.zeros(n)

    def record(self, ks: np.ndarray, per_joint: np.ndarray, miss: np.ndarray, gamma: float) -> np.ndarray:
        """Store the joint errors ``per_joint`` (V, J) at the points ``ks`` (V,) and move their ACI levels by
        ``gamma`` toward the fractions ``miss`` (V,) of joints outside the margin; returns the ring rows
        written (V,). Two scores at one point (forecasts made twice per frame) are stored one after the
        other."""
        if ks.size > 1 and np.unique(ks).size < ks.size:
            return np.concatenate(
                [
                    self.record(ks[i : i + 1], per_joint[i : i + 1], miss[i : i + 1], gamma)
                    for i in range(ks.size)
                ]
            )
        if self.err is None:
            self.err = np.zeros((self.count.size, self.window, per_joint.shape[1]))
        h = self.head[ks]
        self.err[ks, h] = per_joint
        self.head[ks] = (h + 1) % self.window
        self.count[ks] = np.minimum(self.count[ks] + 1, self.window)
        size = per_joint.shape[1]
        self.covered[ks] += size * (1.0 - miss)
        self.scored[ks] += size
        self.alpha_t[ks] = np.clip(self.alpha_t[ks] + gamma * (self.alpha_k[ks] - miss), 0.0, 1.0)
        return h

    def coverage(self) -> np.ndarray:
        """Per point the fraction of joints that fell inside the margin since the start (NaN where none was
        scored)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.scored > 0, self.covered / np.maximum(self.scored, 1), np.nan)


class ForecastArbiter:
    """Scores candidate forecasts against the frames that arrive and combines them (module docstring).

    Args:
        candidates: The candidates' names, the preferred one first.
        horizon: Forecast steps after the newest frame (H).
        dt_s: Time between steps (s): the frame period the forecasts are made at.
        window: Scored forecasts kept per candidate and step.
        min_scores: Scores needed at a step before a candidate can be chosen over the first, and before the
            margin there is taken from the scores at all.
        coverage: Target fraction of joints inside the margin (``1 - alpha``).
        gamma: ACI step size.
        floor_m: Smallest margin (m) (the tracker's noise).
        prior_m: Margin per step (H + 1,) until errors have been seen at that step (m): a stored error
            quantile of the preferred candidate on data it was not trained on (:func:`prior_margins`);
            default 0.1 m at every step.
        warmup: Scores at a step before the ACI quantile alone sets the margin there; until then the margin is
            the larger of that quantile and the prior (:data:`WARMUP`; 0: no warm-up).
        rescale_prior: During the warm-up, widen the prior to the motion scale times the quantile of the
            errors scored at the longest step scored enough, each divided by the motion scale it was
            forecast with (never narrow it): a far step's errors arrive last.
        cold_start_scale: The prior is at least this times the motion scale (:data:`COLD_START_SCALE`; 0:
            the stored prior alone).
        scale_floor_m: The motion scale's floor (m) (:data:`MOTION_SCALE_FLOOR_M`).
        transfer_ratio: Until a step is scored enough, it takes the candidate that has been best at the
            longest step scored enough if that one's mean error there is below ``transfer_ratio`` times the
            preferred candidate's (0: the preferred candidate).
        far_alpha_factor: The ACI's target miss rate falls linearly over the steps from ``1 - coverage`` at
            step 0 to ``far_alpha_factor`` times that at the last step (:data:`FAR_ALPHA_FACTOR`; 1: the same
            target at every step).
        half_steps: Also calibrate the margins halfway between the steps (``half_margins``): the planner
            checks plans between frames, where the person lies between two frames. Each forecast is scored
            there too, the mean of its two steps against the mean of the two frames that have arrived, with
            its own ACI level and quantile (the same window, target halfway between the steps', warm-up and
            scores needed; until then the mean of the two steps' margins). Without it the steps' margins
            are interpolated between them, which covers more than the target there where the frames carry
            independent tracking noise: it averages out between two frames (on simulated operators, tuning
            seeds 1000-1009: 97.7 % of the joints at 80 ms against 95.7 % and 95.5 % at the frames either
            side).
    """

    def __init__(
        self,
        candidates: Sequence[str],
        *,
        horizon: int,
        dt_s: float,
        window: int = 90,
        min_scores: int = MIN_SCORES,
        coverage: float = 0.95,
        gamma: float = 0.005,
        floor_m: float = 0.02,
        prior_m: np.ndarray | None = None,
        warmup: int = WARMUP,
        rescale_prior: bool = True,
        transfer_ratio: float = TRANSFER_RATIO,
        far_alpha_factor: float = FAR_ALPHA_FACTOR,
        cold_start_scale: float = COLD_START_SCALE,
        scale_floor_m: float = MOTION_SCALE_FLOOR_M,
        half_steps: bool = True,
    ) -> None:
        if not candidates:
            raise ValueError("ForecastArbiter needs at least one candidate")
        if not (0.0 < coverage < 1.0):
            raise ValueError(f"coverage must be in (0, 1), got {coverage}")
        if horizon < 1 or not dt_s > 0:
            raise ValueError(f"horizon must be >= 1 and dt_s > 0, got {horizon}, {dt_s}")
        if not (0.0 < far_alpha_factor <= 1.0 / (1.0 - coverage)):
            raise ValueError(f"far_alpha_factor must be in (0, 1 / (1 - coverage)], got {far_alpha_factor}")
        if cold_start_scale < 0 or not scale_floor_m > 0:
            raise ValueError(
                "cold_start_scale must be >= 0 and scale_floor_m > 0, "
                f"got {cold_start_scale}, {scale_floor_m}"
            )
        if window < 1 or min_scores < 1:
            raise ValueError(f"window and min_scores must be >= 1, got {window}, {min_scores}")
        self.candidates = tuple(candidates)
        self.horizon = int(horizon)
        self.dt_s = float(dt_s)
        self.window = int(window)
        self.min_scores = int(min_scores)
        self.alpha = 1.0 - float(coverage)
        self.gamma = float(gamma)
        self.floor_m = float(floor_m)
        self.warmup = int(warmup)
        self.rescale_prior = bool(rescale_prior)
        self.transfer_ratio = float(transfer_ratio)
        self.cold_start_scale = float(cold_start_scale)
        self.scale_floor_m = float(scale_floor_m)
        self.half_steps = bool(half_steps)
        n = self.horizon + 1
        # the ACI's target miss rate per step: ``alpha`` at step 0, ``far_alpha_factor * alpha`` at the last
        self.alpha_k = self.alpha * (1.0 - (1.0 - float(far_alpha_factor)) * np.arange(n) / self.horizon)
        self.half_alpha_k = 0.5 * (self.alpha_k[:-1] + self.alpha_k[1:])  # halfway between the steps
        self.prior_m = (
            np.full(n, 0.1) if prior_m is None else np.asarray(prior_m, dtype=np.float64).reshape(n).copy()
        )
        self._clear()

    def _clear(self) -> None:
        n, W = self.horizon + 1, self.window
        # ring buffers per step: the candidates' mean joint errors and the combined forecast's joint errors
        self._cand_err = np.zeros((len(self.candidates), n, W))
        self._steps = _Ledger(self.alpha_k, W)
        self._scaled_err: np.ndarray | None = None  # (n, W, J): the joint errors over their motion scales
        # forecasts waiting to be scored, in a ring of slots (allocated at the first combine); a slot is
        # scored while its forecast's horizon has not passed
        self._slots = 4 * n
        self._t0 = np.full(self._slots, np.nan)
        self._futures: np.ndarray | None = None  # (slots, C, n, J, 3)
        self._combined: np.ndarray | None = None  # (slots, n, J, 3)
        self._margins_at = np.zeros((self._slots, n))
        self._scale_at = np.ones((self._slots, n))  # the motion scale each stored forecast was made with
        self._next_slot = 0
        # halfway between the steps (``half_steps``): the same bookkeeping, and the last frame scored against
        self._halves = _Ledger(self.half_alpha_k, W)
        self._half_margins_at = np.zeros((self._slots, self.horizon))
        self._last_frame: tuple[float, np.ndarray] | None = None

    @property
    def covered(self) -> np.ndarray:
        """(H + 1,) joints inside the margin, per step, since the start."""
        return self._steps.covered

    @property
    def scored(self) -> np.ndarray:
        """(H + 1,) joints scored, per step."""
        return self._steps.scored

    def reset(self) -> None:
        """Forget everything (a new person)."""
        self._clear()

    # ------------------------------------------------------------------------------------------------
    def score(self, t: float, joints: np.ndarray) -> None:
        """Score the stored forecasts against the frame ``joints`` (J, 3) seen at ``t`` (s)."""
        if self._futures is None or self._combined is None:
            return
        joints = np.asarray(joints, dtype=np.float64)
        if self._scaled_err is None:
            self._scaled_err = np.zeros((self.horizon + 1, self.window, joints.shape[0]))
        last, self._last_frame = self._last_frame, (float(t), joints.copy())
        with np.errstate(invalid="ignore"):
            lag = (t - self._t0) / self.dt_s
            k_all = np.rint(lag)
            due = (k_all >= 1) & (k_all <= self.horizon) & (np.abs(lag - k_all) <= 0.25)
        slots = np.flatnonzero(due)
        if slots.size == 0:
            return
        ks = k_all[slots].astype(np.int64)
        if self.half_steps and last is not None and abs(t - last[0] - self.dt_s) <= 0.25 * self.dt_s:
            self._score_half(slots, ks, last[1], joints)
        cand, per_joint, miss = self._score_due(slots, ks, joints)
        scaled = per_joint / self._scale_at[slots, ks][:, None]
        self._record(ks, cand, per_joint, scaled, miss)

    def _score_due(
        self, slots: np.ndarray, ks: np.ndarray, joints: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The stored forecasts in ``slots`` scored at their steps ``ks`` against ``joints`` (J, 3): each
        candidate's mean joint error (V, C), the combined forecast's joint errors (V, J) and the fraction
        of joints outside its margin (V,) (compiled: :func:`app.prediction._aci_kernels.score_due`)."""
        assert self._futures is not None and self._combined is not None
        return score_due(slots, ks, self._futures, self._combined, self._margins_at, joints)

    def _score_half(self, slots: np.ndarray, ks: np.ndarray, prev: np.ndarray, joints: np.ndarray) -> None:
        """Score the forecasts in ``slots``, due at steps ``ks`` now, halfway between steps ``ks - 1`` and
        ``ks``: the mean of the two steps against the mean of the frame before (``prev``, one step ago) and
        this one (``joints``), and move the ACI levels there."""
        assert self._combined is not None
        js = ks - 1
        mid = self._combined[slots, js] + self._combined[slots, ks]  # (V, J, 3), twice the mean
        err = 0.5 * np.linalg.norm(mid - (prev + joints)[None], axis=-1)  # (V, J)
        miss = np.mean(err > self._half_margins_at[slots, js][:, None], axis=1)
        self._halves.record(js, err, miss, self.gamma)

    def _half_margins(self, margins: np.ndarray) -> np.ndarray:
        """(H,) the margins halfway between the steps, given the steps' ``margins`` (H + 1,): the ACI quantile
        of the half steps' recent errors where scored ``min_scores`` times (no smaller than the steps' mean
        during the warm-up), the mean of the two steps' margins before."""
        between = 0.5 * (margins[:-1] + margins[1:])
        halves = self._halves
        ready = halves.count >= self.min_scores
        if halves.err is None or not np.any(ready):
            return between
        q = self._quantiles(halves)
        warm = halves.count < self.warmup
        out = np.where(ready, np.where(warm, np.maximum(q, between), q), between)
        return np.maximum(out, self.floor_m)

    def _quantiles(self, ledger: _Ledger) -> np.ndarray:
        """Per point of ``ledger`` the ``1 - alpha_t`` quantile of its recent joint errors (compiled:
        :func:`app.prediction._aci_kernels.step_quantiles`, warm-started from the last frame's)."""
        assert ledger.err is not None
        q = step_quantiles(ledger.err, ledger.count, 1.0 - ledger.alpha_t, ledger.q_last)
        ledger.q_last = q
        return q

    def _record(
        self, ks: np.ndarray, cand: np.ndarray, per_joint: np.ndarray, scaled: np.ndarray, miss: np.ndarray
    ) -> None:
        """Store scores at the steps ``ks`` (the joint errors also over their motion scales, ``scaled``) and
        move the ACI levels there."""
        assert self._scaled_err is not None
        h = self._steps.record(ks, per_joint, miss, self.gamma)
        self._cand_err[:, ks, h] = cand.T
        self._scaled_err[ks, h] = scaled

    def combine(self, t0: float, futures: Mapping[str, np.ndarray]) -> ArbitratedForecast:
        """Combine the candidates' forecasts (each (H + 1, J, 3), step 0 the frame at ``t0``) by their recent
        errors, and remember them to be scored."""
        missing = [c for c in self.candidates if c not in futures]
        if missing:
            raise ValueError(f"ForecastArbiter.combine: no forecast from {missing}")
        n = self.horizon + 1
        stored = np.stack([np.asarray(futures[c], dtype=np.float64) for c in self.candidates])
        # per step, the candidate with the lowest mean error over its recent scores (the first until enough)
        count = self._steps.count
        mean = self._cand_err.sum(axis=-1) / np.maximum(count, 1)
        ready = count >= self.min_scores
        best = np.argmin(mean, axis=0)
        fallback = 0
        if self.transfer_ratio > 0 and np.any(ready):
            # the far steps are scored last: until they are, they take the candidate that has been best at
            # the longest step scored enough, if it was clearly better than the preferred one there
            ref = int(np.flatnonzero(ready)[-1])
            if mean[best[ref], ref] < self.transfer_ratio * mean[0, ref]:
                fallback = int(best[ref])
        idx = np.where(ready, best, fallback)
        idx[0] = 0
        joints = stored[idx, np.arange(n)]
        # the motion scale: the largest mean joint displacement any candidate forecasts by each step
        scale = self.scale_floor_m + np.linalg.norm(stored - stored[:, :1], axis=-1).mean(axis=-1).max(axis=0)
        margins = self.margins(scale)
        half = self._half_margins(margins) if self.half_steps else None
        if self._futures is None or self._futures.shape[1:] != stored.shape:
            self._futures = np.zeros((self._slots, *stored.shape))
            self._combined = np.zeros((self._slots, *joints.shape))
            self._t0[:] = np.nan
        assert self._combined is not None
        slot = self._next_slot
        self._t0[slot] = float(t0)
        self._futures[slot] = stored
        self._combined[slot] = joints
        self._margins_at[slot] = margins
        if half is not None:
            self._half_margins_at[slot] = half
        self._scale_at[slot] = scale
        self._next_slot = (slot + 1) % self._slots
        return ArbitratedForecast(
            joints=joints, margins=margins, chosen=tuple(self.candidates[i] for i in idx), half_margins=half
        )

    def margins(self, scale: np.ndarray | None = None) -> np.ndarray:
        """(H + 1,) the adaptive conformal margin (m) per step: the ``1 - alpha_t`` quantile (linear
        interpolation, like ``np.quantile``) of the recent joint errors, no smaller than the prior during the
        warm-up, the prior where fewer than ``min_scores`` were scored. ``scale`` (H + 1,): the person's
        motion scale now (m; default its floor), which the prior follows (module docstring)."""
        if scale is None:
            scale = np.full(self.horizon + 1, self.scale_floor_m)
        prior = np.maximum(self.prior_m, self.cold_start_scale * scale)
        out = prior
        steps = self._steps
        ready = steps.count >= self.min_scores
        if steps.err is not None and np.any(ready):
            q = self._quantiles(steps)
            warm = steps.count < self.warmup
            if self.rescale_prior and np.any(warm | ~ready):
                # the freshest evidence: the longest step scored enough (short steps are scored first)
                assert self._scaled_err is not None
                ref = int(np.flatnonzero(ready)[-1])
                level = min(max(1.0 - float(steps.alpha_t[ref]), 0.0), 1.0)
                factor = np.quantile(self._scaled_err[ref, : steps.count[ref]], level)
                prior = np.maximum(prior, factor * scale)
            out = np.where(ready, np.where(warm, np.maximum(q, prior), q), prior)
        out[0] = min(out[0], self.floor_m)
        return np.maximum(out, self.floor_m)

    def coverage(self, *, halves: bool = False) -> np.ndarray:
        """(H + 1,) fraction of joints that fell inside the margin, per step, since the start (NaN where none
        was scored); with ``halves``, (H,) the same halfway between the steps."""
        return (self._halves if halves else self._steps).coverage()


def prior_margins(
    doc: Mapping[str, Any], kind: str, *, coverage: float, fps: float, horizon: int
) -> np.ndarray:
    """The arbiter's prior (H + 1,) (m) for a ``coverage`` target, from a quantile file's content ``doc``
    (``{"fps": ..., "kinds": {kind: {"p50": [...], "p95": ...}}}``, per step at its ``fps``, step 0 first):
    the stored error quantile of ``kind`` at the smallest stored level not below ``1 - (1 - coverage) /
    COLD_START_MISS_FACTOR`` (the largest stored level if none is), on the ``fps`` grid (linear
    interpolation; held beyond the stored steps)."""
    if kind not in doc.get("kinds", {}):
        raise ValueError(f"no stored error quantiles of {kind!r}")
    quantiles: Mapping[str, Sequence[float]] = doc["kinds"][kind]
    src_fps = float(doc["fps"])
    level = 1.0 - (1.0 - coverage) / COLD_START_MISS_FACTOR
    levels = sorted(int(k[1:]) for k in quantiles if k[0] == "p" and k[1:].isdigit())
    if not levels:
        raise ValueError("no stored error quantile (p50, p95, ...)")
    fit = [q for q in levels if q >= 100.0 * level - 1e-9]
    values = np.asarray(quantiles[f"p{fit[0] if fit else levels[-1]}"], dtype=np.float64)
    src_t = np.arange(values.shape[0]) / float(src_fps)
    return np.interp(np.arange(horizon + 1) / float(fps), src_t, values)
