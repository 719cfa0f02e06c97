"""The exact verification of a planned trajectory against a forecast person, compiled
(:func:`trajectory_first_violation`): the joint limits and the required separation at each sample time,
stopping at the first failure."""

from __future__ import annotations

import math

import numpy as np

from app.planning._kernels.arrays import (
    Clearance,
    ForecastPoses,
    KernelJointLimits,
    Knots,
    PersonCapsules,
    RobotArrays,
)
from app.planning._kernels.base import _jit, _pose_index
from app.planning._kernels.geometry import _person_capsules, _segments_one
from app.planning._kernels.separation import _robot_distance, _too_close

__all__ = ["trajectory_first_violation"]


@_jit
def _hermite_q(
    t: float, k_times: np.ndarray, k_q: np.ndarray, k_qd: np.ndarray, k_h: np.ndarray, out: np.ndarray
) -> None:
    """The cubic Hermite trajectory's configuration (6,) at ``t`` into ``out``
    (:meth:`app.planning.trajectory.Trajectory.q`; held before the first and after the last knot)."""
    K = k_times.shape[0]
    if K == 1:
        for j in range(6):
            out[j] = k_q[0, j]
        return
    i = min(max(_pose_index(k_times, t) - 1, 0), K - 2)
    h = k_h[i]
    s = min(max((t - k_times[i]) / h, 0.0), 1.0)
    s2 = s * s
    s3 = s * s * s
    c0 = 2 * s3 - 3 * s2 + 1
    c1 = (s3 - 2 * s2 + s) * h
    c2 = -2 * s3 + 3 * s2
    c3 = (s3 - s2) * h
    for j in range(6):
        out[j] = c0 * k_q[i, j] + c1 * k_qd[i, j] + c2 * k_q[i + 1, j] + c3 * k_qd[i + 1, j]


@_jit
def trajectory_first_violation(
    ts: np.ndarray,
    tq0: np.ndarray,
    tq1: np.ndarray,
    eps: float,
    knots: Knots,
    limits: KernelJointLimits,
    forecast: ForecastPoses,
    clearance: Clearance,
    robot: RobotArrays,
    person: PersonCapsules,
) -> int:
    """The first sample time ``ts[k]`` (index; -1 if none) at which a trajectory leaves the joint limits or
    breaks the required separation from a forecast person (:meth:`app.planning.search.Planner._verify`).

    The trajectory: cubic Hermite ``knots``, evaluated at ``tq0[k]`` for the sample at wall time ``ts[k]``
    (``tq0 = ts`` for a trajectory in wall time; a path time for a view of it that runs at another speed).
    Limits: ``limits.lo``/``limits.hi`` (6,) less/plus 1e-9 rad. Robot speed: the largest displacement of a
    capsule end between the configurations at ``tq0[k]`` and ``tq1[k]`` (the path time of ``ts[k] + eps``),
    over ``eps``. Person: the ``forecast`` interpolated as :meth:`HumanForecast.poses_at` does (the last pose
    held, the margin growing at ``growth`` m/s up to ``cap``); requirement
    :func:`app.safety.ssm.forecast_clearance` (the ``clearance`` terms), capped at ``floor_m``; from a capsule
    flagged :attr:`PersonCapsules.soft`, only ``Z_d`` (no contact where the person is forecast), and nothing
    at a sample where the robot's speed is at most the capsule's ``clearance.free_mps`` (a contact would stay
    within the region's permissible speed). Samples are checked in order and the check stops at the first
    failure; a NaN counts as a failure.
    """
    knots = Knots(*knots)
    limits = KernelJointLimits(*limits)
    forecast = ForecastPoses(*forecast)
    clearance = Clearance(*clearance)
    robot = RobotArrays(*robot)
    person = PersonCapsules(*person)
    k_times, k_q, k_qd, k_h = knots.times, knots.q, knots.qd, knots.h
    q_lo, q_hi = limits.lo, limits.hi
    fc_times, fc_joints, fc_margins = forecast.times, forecast.joints, forecast.margins
    growth, cap, r_human_max = forecast.growth, forecast.cap, forecast.r_max
    t_r, intrusion_m = clearance.t_reaction_s, clearance.intrusion_m
    z_robot_m, z_human_m, floor_m = clearance.z_robot_m, clearance.z_human_m, clearance.floor_m
    decel, joint_decel, delay = clearance.decel_mps2, clearance.joint_decel_radps2, clearance.delay_s
    jw = clearance.joint_weights
    free = clearance.free_mps
    ra = robot.ra
    ia, ib, rh, soft = person.ia, person.ib, person.rh, person.soft
    N = ts.shape[0]
    L = ra.shape[0]
    M = ia.shape[0]
    H = fc_times.shape[0]
    J = fc_joints.shape[1]
    q0 = np.empty((1, 6))
    q1 = np.empty((1, 6))
    X = np.empty((7, 3))
    Y = np.empty((7, 3))
    Z = np.empty((7, 3))
    soft_k = np.empty(M)
    P = np.empty((7, 3))
    SA = np.empty((L, 3))
    SD = np.empty((L, 3))
    SB = np.empty((L, 4))
    SA1 = np.empty((L, 3))
    SD1 = np.empty((L, 3))
    pose = np.empty((1, J, 3))
    near = np.zeros(L, dtype=np.bool_)
    C = np.empty((M, 6))
    lo = np.empty(3)
    hi = np.empty(3)
    for k in range(N):
        t = ts[k]
        _hermite_q(tq0[k], k_times, k_q, k_qd, k_h, q0[0])
        for j in range(6):
            if not (q0[0, j] >= q_lo[j] - 1e-9 and q0[0, j] <= q_hi[j] + 1e-9):
                return k
        _hermite_q(tq1[k], k_times, k_q, k_qd, k_h, q1[0])
        _segments_one(q0, 0, robot, X, Y, Z, P, SA, SD)
        _segments_one(q1, 0, robot, X, Y, Z, P, SA1, SD1)
        finite = True
        step = 0.0
        for l in range(L):  # noqa: E741
            sa = 0.0
            sb = 0.0
            for j in range(3):
                da = SA1[l, j] - SA[l, j]
                db = (SA1[l, j] + SD1[l, j]) - (SA[l, j] + SD[l, j])
                sa += da * da
                sb += db * db
            m2 = max(sa, sb)
            finite = finite and m2 == m2
            step = max(step, math.sqrt(m2))
        # the forecast pose and margin at t (HumanForecast.poses_at)
        if H == 1:
            i0 = 0
            i1 = 0
            w = 0.0
        else:
            tc = min(max(t, fc_times[0]), fc_times[H - 1])
            i1 = min(max(_pose_index(fc_times, tc), 1), H - 1)
            i0 = i1 - 1
            w = (tc - fc_times[i0]) / (fc_times[i1] - fc_times[i0])
        for j in range(3):
            lo[j] = np.inf
            hi[j] = -np.inf
        for jj in range(J):
            for j in range(3):
                x = fc_joints[i0, jj, j] * (1.0 - w) + fc_joints[i1, jj, j] * w
                pose[0, jj, j] = x
                finite = finite and x == x
                lo[j] = min(lo[j], x)
                hi[j] = max(hi[j], x)
        margin = fc_margins[i0] * (1.0 - w) + fc_margins[i1] * w
        margin = min(margin + growth * max(t - fc_times[H - 1], 0.0), cap)
        if not (finite and margin == margin):
            return k
        v = max(step / eps, 0.0)
        w_top = 0.0  # the braking joint speed (rad/s)
        for j in range(6):
            w_top = max(w_top, abs(q1[0, j] - q0[0, j]) * jw[j])
        w_top /= eps
        req = _robot_distance(v, w_top, t_r, decel, joint_decel, delay)
        req += intrusion_m + z_robot_m + max(z_human_m, margin)
        req = min(req, floor_m)
        any_near = False
        for l in range(L):  # noqa: E741
            g2 = 0.0
            h2 = 0.0
            for j in range(3):
                dd = SD[l, j]
                c = SA[l, j] + 0.5 * dd
                g = max(max((lo[j] - r_human_max) - c, c - (hi[j] + r_human_max)), 0.0)
                g2 += g * g
                h2 += dd * dd
            near[l] = math.sqrt(g2) - (0.5 * math.sqrt(h2) + ra[l]) < req
            any_near = any_near or near[l]
        if not any_near:
            continue
        _person_capsules(pose, 0, ia, ib, C)
        for m in range(M):  # a contact-only capsule the robot may touch at this speed asks nothing
            soft_k[m] = 2.0 if soft[m] > 0.0 and v <= free[m] else soft[m]
        if _too_close(SA, SD, near, ra, C, rh, req, SB, soft_k, min(z_human_m, req)):
            return k
    return -1
