"""SSM-aware timing of plans: a path timed with the speed scale the governor will really allow.

The search times its moves at the robot's full joint speeds, but near a person the ISO/TS 15066 speed
governor (:mod:`app.safety.governor`) slows the robot down, often to a small fraction of that. A plan timed at
full speed says it arrives long before it does, and it is checked against the forecast person at instants
when the robot will not be there. :func:`predicted_scales` walks along a fitted path, asks the forecast where
the person will be when the robot gets to each point, and predicts the governor's scale there
(:meth:`app.safety.governor.GovernorModel.scale`, the same separation model, brake and worst-case person as
the governor itself). The planner verifies the path at that timing (:class:`PredictedTiming`) against
the forecast (:meth:`app.planning.search.Planner.plan` with ``timing``) and reports the predicted arrival;
the robot executes the path at its full-speed timing under the governor, so it can still go faster than
predicted where the person turns out farther away.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.planning._kernels.timing import TimingGovernor, TimingPath, TimingPerson, predicted_scales_kernel
from app.planning.trajectory import Trajectory, sample_times
from app.safety.governor import BRAKE_INSTANTS, SCALE_GRID, GovernorModel
from app.safety.stopping import UR5E_STOP

__all__ = ["PredictedTiming", "part_speeds", "predicted_arrival_from", "predicted_scales"]

#: Spacing (s of path time at full speed) of the points at which the governor's scale is predicted.
STEP_S = 0.04


def part_speeds(collision: Any, q: np.ndarray, qd: np.ndarray, *, fd_step_s: float = 1e-3) -> np.ndarray:
    """(K, L) speed (m/s) of each robot part for configurations ``q`` and joint velocities ``qd`` (K, 6):
    that of the faster end of the part's capsule axis (on a rigid link no point of the axis moves faster,
    so it bounds the speed of the capsule's whole surface)."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
    qd = np.asarray(qd, dtype=np.float64).reshape(-1, 6)
    a0, b0, _ = collision.robot_capsules(q)
    a1, b1, _ = collision.robot_capsules(q + fd_step_s * qd)
    va = np.linalg.norm(a1 - a0, axis=-1)
    vb = np.linalg.norm(b1 - b0, axis=-1)
    return np.maximum(va, vb) / fd_step_s


def _ahead_max(x: np.ndarray, n: int) -> np.ndarray:
    """Per row i the maximum of rows i..i+n (clipped at the end)."""
    out = x.copy()
    # beyond the last row there is nothing to take (a path of no duration looks ahead ~1e8 rows)
    for k in range(1, min(n, x.shape[0] - 1) + 1):
        out[:-k] = np.maximum(out[:-k], x[k:])
    return out


def predicted_scales(
    traj: Trajectory, forecast: Any, collision: Any, model: GovernorModel, *, step_s: float = STEP_S
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walk along ``traj`` at the governor's predicted scale (compiled:
    :func:`app.planning._kernels.timing.predicted_scales_kernel`; the tests compare it with a NumPy
    reference).

    At each sample point the forecast person at the wall time the robot gets there (and a speed window
    earlier) gives each part's separation, the person's directed speed toward it
    (:func:`app.safety.governor.directed_approach`) and the part's speed toward the person held there
    (the path's average closing to the points of :func:`app.planning._kernels.timing.toward_steps`), and
    :meth:`GovernorModel.scale` the scale of the move to the next point, at least ``model.min_scale``.

    Args:
        traj: The path, timed at full speed.
        forecast: The person (:class:`app.prediction.forecast.Forecast`: ``times``, ``joints``).
        collision: The collision model (``robot_capsules``, ``human_capsules``).
        model: The governor's model.
        step_s: Spacing of the sample points (s of path time).

    Returns:
        ``(tau, t, scale)``: path times (N + 1,) of the sample points on ``traj``'s own clock (its knots'
        times, at full speed), the predicted wall time (N + 1,) at which the robot gets to each (the first is
        ``traj.t_start``), and the scale (N,) predicted for the move from each point to the next.
    """
    t0, t1 = traj.t_start, traj.t_end
    n = max(math.ceil((t1 - t0) / step_s), 1)
    tau = np.linspace(t0, t1, n + 1)
    q = traj.q(tau)
    qd = traj.qd(tau)
    ahead = max(round(model.lookahead_s / max((t1 - t0) / n, 1e-9)), 0)
    v = _ahead_max(part_speeds(collision, q, qd), ahead)  # (N + 1, L) what the governor brakes for
    w = _ahead_max(np.atleast_1d(UR5E_STOP.braking_speed(qd)), ahead)  # the braking joint speed
    ra, rb, rr = collision.robot_capsules(q)
    ha, hb, hr = collision.human_capsules(np.asarray(forecast.joints, dtype=np.float64))
    path = TimingPath(tau, _f64(ra), _f64(rb - ra), _f64(rr), _f64(v), _f64(w))
    person = TimingPerson(_f64(forecast.times), _f64(ha), _f64(hb - ha), _f64(hr))
    t, scales = predicted_scales_kernel(path, person, _governor_arrays(model, ahead, hr.shape[0]), float(t0))
    return tau, t, scales


def _f64(x: Any) -> np.ndarray:
    return np.ascontiguousarray(x, dtype=np.float64)


def _governor_arrays(model: GovernorModel, ahead: int, n_caps: int) -> TimingGovernor:
    """``model`` as the compiled walk reads it, its look-ahead ``ahead`` sample points, for a person of
    ``n_caps`` capsules."""
    misc = (
        model.tracking_margin_m,
        model.speed_window_s,
        model.sensing_age_s,
        model.near_band_m,
        model.speed_noise_mps,
        model.min_scale,
        model.brake_decel_mps2,
        model.brake_joint_decel,
        float(ahead),
        1.0 if model.robot_toward else 0.0,
    )
    law = np.zeros(0) if model.law is None else model.law.kernel_params
    caps = model.caps_for(n_caps)
    return TimingGovernor(
        _f64(model.separation.kernel_params),
        _f64(law),
        _f64(SCALE_GRID),
        _f64(BRAKE_INSTANTS),
        _f64(misc),
        caps,
        _f64(np.unique(np.append(caps, -1.0))),
        model.floors_for(n_caps),
    )


class PredictedTiming:
    """A trajectory as the robot will run it under the governor: at wall time ``t`` the robot is at path time
    ``tau(t)`` of ``traj``, from :func:`predicted_scales`.

    The planner verifies a plan through it against the forecast person (where they will be when the robot
    really gets to each point), while the robot executes ``traj`` itself: the governor may then run it faster
    than predicted where the person turns out farther away, up to the path's full speed. It offers what the
    planner's check reads of a trajectory (``q``, ``t_start``, ``t_end``, ``sample``) and names the
    trajectory it warps (``base_trajectory``, ``path_times``), so the compiled check evaluates ``traj``'s
    knots at the warped times.
    """

    def __init__(self, traj: Trajectory, tau: np.ndarray, t: np.ndarray) -> None:
        if tau.shape != t.shape or tau.ndim != 1 or tau.size < 2 or np.any(np.diff(t) <= 0):
            raise ValueError("PredictedTiming needs increasing wall times, one per path time")
        self.traj = traj
        self._tau = np.asarray(tau, dtype=np.float64)
        self._t = np.asarray(t, dtype=np.float64)

    @classmethod
    def of(
        cls, traj: Trajectory, forecast: Any, collision: Any, model: GovernorModel, *, step_s: float = STEP_S
    ) -> PredictedTiming:
        tau, t, _ = predicted_scales(traj, forecast, collision, model, step_s=step_s)
        return cls(traj, tau, t)

    @property
    def base_trajectory(self) -> Trajectory:
        return self.traj

    def path_times(self, t: Any) -> np.ndarray:
        """Path times of ``traj`` at wall times ``t`` (held at the ends)."""
        return np.interp(np.asarray(t, dtype=np.float64), self._t, self._tau)

    @property
    def t_start(self) -> float:
        return float(self._t[0])

    @property
    def t_end(self) -> float:
        return float(self._t[-1])

    @property
    def duration(self) -> float:
        return self.t_end - self.t_start

    def q(self, t: Any) -> np.ndarray:
        return self.traj.q(self.path_times(t))

    def sample(self, dt_s: float, *, t_from: float | None = None, t_to: float | None = None) -> np.ndarray:
        a = self.t_start if t_from is None else float(t_from)
        b = self.t_end if t_to is None else float(t_to)
        return sample_times(a, b, dt_s)


class _Remainder:
    """The rest of ``traj`` from its path time ``tau_b`` on, as a path that starts at wall time ``t_b``."""

    def __init__(self, traj: Any, tau_b: float, t_b: float) -> None:
        self._traj, self._shift = traj, float(tau_b) - float(t_b)
        self.t_start = float(t_b)
        self.t_end = float(t_b) + max(float(traj.t_end) - float(tau_b), 0.0)

    def q(self, t: Any) -> np.ndarray:
        return self._traj.q(np.asarray(t, dtype=np.float64) + self._shift)

    def qd(self, t: Any) -> np.ndarray:
        return self._traj.qd(np.asarray(t, dtype=np.float64) + self._shift)


def predicted_arrival_from(
    traj: Any, tau_b: float, t_b: float, forecast: Any, collision: Any, model: GovernorModel
) -> float:
    """The predicted arrival (wall time) of the rest of ``traj`` from its path time ``tau_b``, reached at
    wall time ``t_b``, under the governor (:func:`predicted_scales` against ``forecast``): what the supervisor
    weighs a backup from a branch point against."""
    rest = _Remainder(traj, tau_b, t_b)
    if rest.t_end <= rest.t_start:
        return rest.t_end
    _, t, _ = predicted_scales(rest, forecast, collision, model)  # type: ignore[arg-type]
    return float(t[-1])
