"""Compiled inner loops of the speed governor (numba): run per servo tick on the robot's parts.

:func:`max_scale` is the loop form of ``max_scale_reference`` and :func:`governed_scale` of
``governed_scale_reference``, NumPy references kept with the tests (``tests/governor_reference.py``);
the tests compare each kernel with its reference. They run per servo tick on arrays of seven robot
parts, where NumPy's per-call cost (about a microsecond per operation, dozens to hundreds per call) is most
of the time.

The arithmetic is written in the references' order of operations and compiled without ``fastmath``, so the
results agree to rounding. ``cache=True`` keeps the machine code next to this file (numba compiles in
memory with a warning where that folder is read-only).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from app.jit import jit

__all__ = [
    "PFLLevels",
    "PartSeparation",
    "RobotMotion",
    "ServoGovernor",
    "approach",
    "governed_scale",
    "law_scale",
    "max_scale",
    "pfl_extra",
]


class PartSeparation(NamedTuple):
    """The governor's last measurement of the person, per robot part (L,), as :func:`governed_scale` reads
    it (built once per camera frame).

    Attributes:
        sep_m: Each part's separation from the person at the measurement, less the tracking margin (m).
        x_h0: The person's worst-case approach from the middle of the speed window to the frame (m), already
            in ``sep_m``.
        v_h0: The person's approach speed toward each part, measured over the window (m/s).
        pfl: Power and force limiting inside ``S_p`` (:class:`PFLLevels`).
    """

    sep_m: np.ndarray
    x_h0: np.ndarray
    v_h0: np.ndarray
    pfl: PFLLevels


class PFLLevels(NamedTuple):
    """Power and force limiting inside ``S_p``, per robot part (:func:`app.safety.pfl.pfl_levels`): a part
    closing on the person at ``v`` must keep ``S_p`` from the capsules whose permissible contact speed is
    below ``v`` only, at ``extra[l, k]`` beyond its nearest separation, ``k`` the last of ``levels`` below
    ``v``. ``levels[0]`` is -1 (the capsules that admit no contact).

    Attributes:
        levels: (K,) the capsules' distinct permissible speeds (m/s), ascending.
        extra: (L, K) the separation beyond each part's nearest one that SSM keeps at each level (m).
        v_h: (L, K) the person's approach speed toward each part of the capsules at or below each level
            (m/s; ISO 13855's by region, the measured one where faster; inf: the part's own ``v_h`` alone):
            the governor takes the lesser of it and the part's.
    """

    levels: np.ndarray
    extra: np.ndarray
    v_h: np.ndarray


class RobotMotion(NamedTuple):
    """The robot's own motion as :func:`governed_scale` reads it, per robot part (L,) (built per tick).

    ISO/TS 15066 5.5.4.2.3 takes the robot's speed *in the direction of the operator* for ``S_r`` and ``S_s``;
    the stopping time ``T_s`` is the robot's, from the speed it really has.

    Attributes:
        v_part: Each part's fastest speed over the look-ahead at scale 1 (m/s): whether the robot moves.
        v_toward: Each part's speed toward the person at scale 1 (m/s, at most ``v_part``; negative: moving
            away): a bound of how fast its motion along the path closes its separation, over the look-ahead.
        closed_m: How much of the measured separation each part's own motion may have closed since the
            measurement (a bound, m).
    """

    v_part: np.ndarray
    v_toward: np.ndarray
    closed_m: np.ndarray


class ServoGovernor(NamedTuple):
    """The servo governor's constants as :func:`governed_scale` reads them (built once per law).

    Attributes:
        separation: ``(s0_m, t_reaction_s, stop_decel_mps2, human_speed_max_mps, human_accel_mps2)`` of the
            separation model (:attr:`app.safety.governor.SeparationModel.kernel_params`).
        law: The speed-scaling law's ``(T_r + T_s, C + Z_d + Z_r, T_r + T_s / 2)``, or empty (none).
        scales: The grid of scales of the braking envelope (:data:`app.safety.governor.SCALE_GRID`).
        env_u: The instants of a brake, as fractions of it (:data:`app.safety.governor.BRAKE_INSTANTS`).
    """

    separation: np.ndarray
    law: np.ndarray
    scales: np.ndarray
    env_u: np.ndarray


@jit(inline="always")
def approach(v0: float, dt: float, v_max_h: float, accel: float) -> tuple[float, float]:
    """Worst-case approach distance (m) and speed (m/s) of a person ``dt`` (s) after moving at ``v0``."""
    if dt < 0.0:
        dt = 0.0
    vmax = max(v_max_h, v0)
    if accel <= 0.0:
        return v0 * dt, v0
    t1 = (vmax - v0) / accel
    acc = min(dt, t1)
    dist = v0 * acc + 0.5 * accel * acc * acc + vmax * max(dt - t1, 0.0)
    return dist, min(v0 + accel * dt, vmax)


@jit(inline="always")
def _sp(v_part: float, t_s: float, v_human: float, s0: float, t_r: float) -> float:
    """``S_p`` (m) of a part closing at ``v_part`` on a robot that stops in ``t_s`` (s): the compiled twin of
    :func:`app.safety.ssm.required_separation`, in its order of operations."""
    v_part = max(v_part, 0.0)
    return max(v_human, 0.0) * (t_r + t_s) + (v_part * t_r + v_part * (0.5 * t_s) + s0)


@jit(inline="always")
def _pfl_level(v: float, levels: np.ndarray) -> int:
    """The level (:class:`PFLLevels`) whose capsules a part closing at ``v`` (m/s) must keep ``S_p`` from:
    the last whose permissible speed is below ``v``."""
    k = 0
    for j in range(1, levels.shape[0]):
        if levels[j] < v:
            k = j
    return k


@jit
def _scale_ok(
    sc: float,
    d: np.ndarray,
    vh: np.ndarray,
    vp: np.ndarray,
    rate: float,
    env_u: np.ndarray,
    params: np.ndarray,
    levels: np.ndarray,
    extra: np.ndarray,
    v_lv: np.ndarray,
) -> bool:
    s0, t_r, v_max_h, accel = params[0], params[1], params[3], params[4]
    r = max(rate, 1e-6)
    for i in range(d.shape[0]):
        a = rate * vp[i]
        v = sc * vp[i]
        # power and force limiting: the capsules this part may touch at v need no S_p (braking only slows it)
        lv = _pfl_level(v, levels)
        d_i = d[i] + extra[i, lv]
        if d_i == np.inf:
            continue
        vh_i = min(vh[i], v_lv[i, lv])
        for k in range(env_u.shape[0]):
            t = env_u[k] * sc / r
            x_h, v_h = approach(vh_i, t, v_max_h, accel)
            travel = v * t - 0.5 * a * t * t
            s_t = sc - rate * t
            need = _sp(s_t * vp[i], s_t / r, v_h, s0, t_r)
            if not (d_i - x_h - travel - need >= 0.0):
                return False
    return True


@jit
def max_scale(
    d: np.ndarray,
    vh: np.ndarray,
    vp: np.ndarray,
    rate: float,
    lo: float,
    hi: float,
    scales: np.ndarray,
    env_u: np.ndarray,
    params: np.ndarray,
    levels: np.ndarray,
    extra: np.ndarray,
    v_lv: np.ndarray,
) -> float:
    """Largest safe path-speed scale in ``[lo, hi]`` for parts at separations ``d`` (L,) (m), the person
    approaching each at ``vh`` (L,) (m/s), the parts closing on the person at ``s * vp`` (L,) (m/s; negative:
    moving away), a brake lowering the scale at ``rate`` (1/s): the robot's stopping time from scale ``s`` is
    ``s / rate``, the stopping model's (:mod:`app.safety.stopping`; the brake's rate is the slower of its
    fastest point's and fastest joint's deceleration). ``scales``: the grid; ``env_u``: the instants of a
    brake (fractions of it); ``params``: ``(s0_m, t_reaction_s, stop_decel_mps2, human_speed_max_mps,
    human_accel_mps2)``; ``levels``, ``extra``, ``v_lv``: power and force limiting (:class:`PFLLevels`;
    ``[-1]``, zeros (L, 1) and inf (L, 1): SSM alone)."""
    n = d.shape[0]
    if n == 0:
        return 1.0
    s0, t_r, v_max_h, accel = params[0], params[1], params[3], params[4]
    lo = max(lo, 0.0)
    hi = min(hi, 1.0)
    # quick accept (most ticks): every term at its largest over a brake from the highest scale asked for
    t_b = hi / max(rate, 1e-6)
    quick = True
    for i in range(n):
        x_b, v_b = approach(vh[i], t_b, v_max_h, accel)
        # (a part moving away gains separation over the brake, but none at its start)
        worst = _sp(hi * vp[i], t_b, v_b, s0, t_r) + x_b + hi * max(vp[i], 0.0) * t_b
        if not (d[i] >= worst):
            quick = False
            break
    if quick:
        return hi
    # the candidates in increasing order: lo, the grid strictly inside (lo, hi), hi; the answer is the
    # last one of the leading run of safe ones
    if not _scale_ok(lo, d, vh, vp, rate, env_u, params, levels, extra, v_lv):
        return 0.0
    if not hi > lo:
        return lo
    best = lo
    for j in range(scales.shape[0]):
        sc = scales[j]
        if sc - lo > 0.0 and sc - hi < 0.0:
            if not _scale_ok(sc, d, vh, vp, rate, env_u, params, levels, extra, v_lv):
                return best
            best = sc
    if _scale_ok(hi, d, vh, vp, rate, env_u, params, levels, extra, v_lv):
        return hi
    return best


@jit(inline="always")
def _law_one(d: float, v_nom: float, v_h: float, law: np.ndarray) -> float:
    """ISO/TS 15066 speed-scaling law of one part (:func:`app.safety.ssm.speed_scale`); ``law``:
    ``(T_r + T_s, C + Z_d + Z_r, T_r + T_s / 2)``."""
    v_h = max(v_h, 0.0)
    slack = d - v_h * law[0] - law[1]
    v_max = max(slack, 0.0) / law[2]
    if not math.isfinite(d):
        return 1.0 if d > 0 else 0.0
    if v_nom <= 1e-9:
        return 1.0 if v_max > 0.0 else 0.0
    return min(1.0, v_max / max(v_nom, 1e-300))


@jit
def law_scale(
    d: np.ndarray,
    v_nom: np.ndarray,
    v_h: np.ndarray,
    law: np.ndarray,
    levels: np.ndarray,
    extra: np.ndarray,
    v_lv: np.ndarray,
) -> float:
    """The smallest scale of the speed-scaling law over parts (L,) (1 for none), with power and force
    limiting (:class:`PFLLevels`): at level ``k`` the part keeps the law's ``S_p`` from the capsules up to
    that level and closes on the others no faster than the next level's permissible speed."""
    out = 1.0
    n_lv = levels.shape[0]
    for i in range(d.shape[0]):
        best = 0.0
        for k in range(n_lv):
            if extra[i, k] == np.inf:
                s_k = 1.0
            else:
                s_k = _law_one(d[i] + extra[i, k], v_nom[i], min(v_h[i], v_lv[i, k]), law)
            if k + 1 < n_lv and v_nom[i] > 1e-9:
                s_k = min(s_k, levels[k + 1] / v_nom[i])
            best = max(best, s_k)
        out = min(out, best)
    return out


@jit
def governed_scale(
    parts: PartSeparation,
    robot: RobotMotion,
    dt_h: float,
    s: float,
    dt: float,
    rate: float,
    lo: float,
    hi: float,
    governor: ServoGovernor,
) -> float:
    """The speed governor's target scale for the next tick (parts (L,)).

    The separation of each part at the next tick is bounded below from the last measurement ``parts.sep_m``
    (m), the person's worst-case approach since (from ``parts.v_h0`` (m/s), ``dt_h`` (s) after the
    measurement, less the ``parts.x_h0`` (m) already counted; NaN ``dt_h``: no measurement, the fastest
    approach), what the part's own motion closed since (``robot.closed_m``) and may close this tick
    (``s * robot.v_toward * dt``). The target is the braking envelope's largest safe scale in ``[lo, hi]``
    (:func:`max_scale`, the parts closing at ``robot.v_toward``) over every part when any part moves
    (``robot.v_part > 1e-4`` m/s), limited by the speed-scaling law at the measured ``v_h0`` when
    ``governor.law`` is not empty (:func:`law_scale`)."""
    sep_m, x_h0, v_h0 = parts.sep_m, parts.x_h0, parts.v_h0
    vmax, toward, closed = robot.v_part, robot.v_toward, robot.closed_m
    params, law = governor.separation, governor.law
    n = sep_m.shape[0]
    v_max_h, accel = params[3], params[4]
    d = np.empty(n)
    vh = np.empty(n)
    vp = np.empty(n)
    vm = np.empty(n)
    # a robot that moves at all is judged by every part: a part at rest on a moving robot must keep its
    # S_p too (ISO/TS 15066 asks the robot, not the part, to be at standstill within S_p)
    moving = False
    for i in range(n):
        if vmax[i] > 1e-4:
            moving = True
    k = 0
    for i in range(n):
        if moving:
            if math.isnan(dt_h):
                sep_lb, v_h = sep_m[i], v_max_h
            else:
                x1, v_h = approach(v_h0[i], dt_h, v_max_h, accel)
                sep_lb = sep_m[i] - (x1 - x_h0[i]) - closed[i]
            d[k] = sep_lb - s * toward[i] * dt
            vh[k] = v_h
            vp[k] = toward[i]
            vm[k] = max(v_h0[i], 0.0)
            k += 1
    lv, extra, v_lv = parts.pfl.levels, parts.pfl.extra, parts.pfl.v_h
    target = max_scale(
        d[:k], vh[:k], vp[:k], rate, lo, hi, governor.scales, governor.env_u, params, lv, extra, v_lv
    )
    if law.shape[0] > 0 and k > 0:
        target = min(target, max(law_scale(d[:k], vp[:k], vm[:k], law, lv, extra, v_lv), 0.0))
    return target


@jit
def pfl_extra(
    d: np.ndarray,
    v: np.ndarray,
    caps: np.ndarray,
    levels: np.ndarray,
    band: float,
    out: np.ndarray,
    out_v: np.ndarray,
) -> None:
    """``out`` (L, K): each part's separation from the capsules whose permissible speed is at most each of
    ``levels``, beyond its nearest separation (inf where none is), from the distances ``d`` (L, M); ``out_v``
    (L, K): the fastest approach ``v`` (L, M) of those capsules within ``band`` of their nearest: the
    compiled twin of :func:`app.safety.pfl.pfl_levels`."""
    for p in range(d.shape[0]):
        near = np.inf
        for m in range(d.shape[1]):
            near = min(near, d[p, m])
        for k in range(levels.shape[0]):
            best = np.inf
            for m in range(d.shape[1]):
                if caps[m] <= levels[k]:
                    best = min(best, d[p, m])
            out[p, k] = max(best - near, 0.0) if best < np.inf else np.inf
            vk = 0.0 if best < np.inf else np.inf
            for m in range(d.shape[1]):
                if caps[m] <= levels[k] and d[p, m] <= best + band:
                    vk = max(vk, v[p, m])
            out_v[p, k] = vk
