"""NumPy references of the speed governor's compiled loops, for the tests only (the product never imports
them): the braking envelope's largest safe scale (:func:`app.safety._kernels.max_scale`), the servo tick's
target scale (:func:`app.safety._kernels.governed_scale`) and the governor's scale predicted along a path
(:func:`app.planning._kernels.timing.predicted_scales_kernel`), and power and force limiting's separations
per permissible speed (:func:`app.safety.pfl.pfl_levels`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from app.control.supervisor import Supervisor
from app.planning.ssm_timing import STEP_S, _ahead_max, part_speeds
from app.safety.governor import BRAKE_INSTANTS, SCALE_GRID, GovernorModel, SeparationModel, directed_approach
from app.safety.ssm import required_separation
from app.safety.stopping import UR5E_STOP


def _sp(model: SeparationModel, v_part: Any, t_s: Any, v_human: Any) -> Any:
    """``S_p`` (m) of a part closing at ``v_part`` on a robot that stops in ``t_s`` (s) (broadcast): the one
    formula, :func:`app.safety.ssm.required_separation`."""
    t_r, s0 = model.t_reaction_s, model.s0_m
    return required_separation(v_human, v_part, t_reaction_s=t_r, t_stop_s=t_s, constant_m=s0)


def max_scale_reference(
    model: SeparationModel,
    separation_m: np.ndarray,
    *,
    v_human_mps: np.ndarray,
    v_parts_mps: np.ndarray,
    rate: float,
    lo: float = 0.0,
    hi: float = 1.0,
) -> float:
    """:meth:`SeparationModel.max_scale` of ``model`` in NumPy, over the whole envelope at once."""
    d1 = np.asarray(separation_m, dtype=np.float64)
    vh1 = np.asarray(v_human_mps, dtype=np.float64)
    vp1 = np.asarray(v_parts_mps, dtype=np.float64)
    if d1.size == 0:
        return 1.0
    lo, hi = max(float(lo), 0.0), min(float(hi), 1.0)
    # quick accept (most ticks): every term at its largest over a brake from the highest scale asked for
    t_b = hi / max(rate, 1e-6)
    x_b, v_b = model.human_approach(vh1, t_b)
    worst = _sp(model, hi * vp1, t_b, v_b) + x_b + hi * np.maximum(vp1, 0.0) * t_b
    if bool(np.all(d1 >= worst)):
        return hi
    inside = (SCALE_GRID - lo > 0.0) & (SCALE_GRID - hi < 0.0)
    scales = SCALE_GRID[inside]
    scales = np.concatenate([[lo], scales, [hi]]) if hi > lo else np.array([lo])
    d, vh0, vp = d1[:, None, None], vh1[:, None, None], vp1[:, None, None]
    sc = scales[None, :, None]
    t = BRAKE_INSTANTS[None, None, :] * sc / max(rate, 1e-6)
    x_h, v_h = model.human_approach(vh0, t)
    a = rate * vp
    v = sc * vp
    travel = v * t - 0.5 * a * t**2
    s_t = sc - rate * t  # the scale during the brake
    need = _sp(model, s_t * vp, s_t / max(rate, 1e-6), v_h)
    ok = np.all(d - x_h - travel - need >= 0.0, axis=2).all(axis=0)  # (NS,) every part
    n_ok = int(np.cumprod(ok).sum())
    return float(scales[n_ok - 1]) if n_ok > 0 else 0.0


def separation_bound(sup: Supervisor, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Per robot part: a lower bound of the separation at time ``t`` (m) and an upper bound of the
    person's approach speed then (m/s), from the last measurement, the person's worst case since, and
    the part's travel (as the compiled governor computes them)."""
    parts = sup._parts
    if not math.isfinite(sup._v_h_t):
        return parts.sep_m.copy(), np.full(sup.n_parts, sup.ssm.human_speed_max_mps)
    x1, v1 = sup.ssm.human_approach(parts.v_h0, t - sup._v_h_t)
    return parts.sep_m - (x1 - parts.x_h0), np.asarray(v1)


def governed_scale_reference(
    sup: Supervisor, t: float, dt: float, s: float, vmax: np.ndarray, rate: float, lo: float, hi: float
) -> float:
    """``sup._governed_scale`` (the compiled servo tick) in NumPy."""
    robot = sup._robot_motion(vmax, dt, rate, hi)
    toward = robot.v_toward
    # separation lower bound of each part at the next tick
    sep_lb, v_h = separation_bound(sup, t + dt)
    if math.isfinite(sup._v_h_t):  # what the robot closed counts from a measurement (none: not measured)
        sep_lb = sep_lb - robot.closed_m
    sep_lb = sep_lb - s * toward * dt
    m = np.full(vmax.shape, bool(np.any(vmax > 1e-4)))  # every part of a robot that moves
    s_target = max_scale_reference(
        sup.ssm,
        sep_lb[m],
        v_human_mps=v_h[m],
        v_parts_mps=toward[m],
        rate=rate,
        lo=lo,
        hi=hi,
    )
    if sup.speed_scale_law is not None and np.any(m):
        # the standard's law with the person's measured speed (the envelope above already covers
        # their worst-case speed-up since it was measured, with the stopping time of this speed)
        law = sup.speed_scale_law(sep_lb[m], toward[m], np.maximum(sup._parts.v_h0[m], 0.0))
        s_target = min(s_target, max(law, 0.0))
    return s_target


def predicted_scales_reference(
    traj: Any, forecast: Any, collision: Any, model: GovernorModel, *, step_s: float = STEP_S
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`app.planning.ssm_timing.predicted_scales` as a NumPy loop: one forecast query, one paired
    distance call and one :meth:`GovernorModel.scale` per sample point."""
    t0, t1 = traj.t_start, traj.t_end
    n = max(math.ceil((t1 - t0) / step_s), 1)
    tau = np.linspace(t0, t1, n + 1)
    q = traj.q(tau)
    qd = traj.qd(tau)
    ahead = max(round(model.lookahead_s / max((t1 - t0) / n, 1e-9)), 0)
    v = _ahead_max(part_speeds(collision, q, qd), ahead)
    w = _ahead_max(np.atleast_1d(UR5E_STOP.braking_speed(qd)), ahead)
    window = model.speed_window_s
    t = np.empty(n + 1)
    t[0] = t0
    scales = np.empty(n)
    for i in range(n):
        joints, _ = forecast.poses_at(np.array([t[i], t[i] - window]))
        d = collision.pair_distances(q[i], joints)  # (2, L, M)
        sep, v_h = directed_approach(d[0], d[1], window, band_m=model.near_band_m)
        v_parts = np.maximum(v[i], v[i + 1])
        toward = v_parts
        if model.robot_toward:  # the path's average closing on the person held where they are then
            steps = sorted({min(i + 1, n), min(i + max(ahead // 2, 1), n), min(i + max(ahead, 1), n)})
            held = joints[:1]
            rates = [
                (sep - collision.pair_distances(q[j], held)[0].min(axis=1)) / max(tau[j] - tau[i], 1e-12)
                for j in steps
                if j > i
            ]
            toward = np.minimum(np.max(rates, axis=0), v_parts)
            toward = np.where(toward > 0.0, v_parts, toward)  # a closing part: its whole speed
        s = model.scale(sep, v_h, v_parts, float(max(w[i], w[i + 1])), toward)
        scales[i] = max(s, model.min_scale)
        t[i + 1] = t[i] + (tau[i + 1] - tau[i]) / scales[i]
    return tau, t, scales


def pfl_levels_reference(
    d_pairs: np.ndarray, caps_mps: np.ndarray, v_pairs: np.ndarray | None = None, *, band_m: float = 0.25
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The NumPy form of :func:`app.safety.pfl.pfl_levels` (which runs the compiled
    :func:`app.safety._kernels.pfl_extra`)."""
    d = np.asarray(d_pairs, dtype=np.float64)
    caps = np.asarray(caps_mps, dtype=np.float64)
    levels = np.unique(np.append(caps, -1.0))
    nearest = d.min(axis=1)
    extra = np.full((d.shape[0], levels.shape[0]), np.inf)
    v_h = np.full((d.shape[0], levels.shape[0]), np.inf)
    for k, c in enumerate(levels):
        sel = caps <= c
        if not sel.any():
            continue
        d_sel = d[:, sel]
        near_k = d_sel.min(axis=1)
        extra[:, k] = np.maximum(near_k - nearest, 0.0)
        if v_pairs is not None:
            v_sel = np.asarray(v_pairs, dtype=np.float64)[:, sel]
            v_h[:, k] = np.where(d_sel <= near_k[:, None] + band_m, v_sel, 0.0).max(axis=1)
    return levels, extra, v_h
