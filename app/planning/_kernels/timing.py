"""Compiled loop of the SSM-aware timing (numba): the governor's scale predicted along a path.

:func:`predicted_scales_kernel` is the loop of :func:`app.planning.ssm_timing.predicted_scales`: it walks
along a path, asks the forecast where the person will be when the robot gets to each point (the wall time
there depends on every scale before it, so the walk is sequential), measures the separation, the person's
directed speed and each part's speed toward the person (at the points of :func:`toward_steps`) as the
supervisor would, and applies the governor's model (:meth:`app.safety.governor.GovernorModel.scale`, with
the governor's own compiled envelope and law, :func:`app.safety.governor.max_scale` and
:func:`app.safety.governor.law_scale`). The NumPy loop it replaces
is kept with the tests (``tests/governor_reference.py``), which compare the two.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from app.jit import jit
from app.planning._kernels.base import _seg_dist
from app.safety.governor import approach, law_scale, max_scale
from app.safety.pfl import pfl_extra

__all__ = ["TimingGovernor", "TimingPath", "TimingPerson", "predicted_scales_kernel", "toward_steps"]


class TimingPath(NamedTuple):
    """The path, sampled at ``N + 1`` points of its own (full-speed) clock.

    Attributes:
        tau: Path times (N + 1,) (s).
        ra: Robot capsule starts (N + 1, L, 3) (m).
        rd: Robot capsule axes, end minus start (N + 1, L, 3) (m).
        rr: Robot capsule radii (L,) (m).
        v: Each part's speed at scale 1 over the governor's look-ahead (N + 1, L) (m/s).
        w: The fastest joint's speed at scale 1 over the look-ahead (N + 1,) (rad/s).
    """

    tau: np.ndarray
    ra: np.ndarray
    rd: np.ndarray
    rr: np.ndarray
    v: np.ndarray
    w: np.ndarray


class TimingPerson(NamedTuple):
    """The forecast person as capsules at the forecast's frames, linear in between, held beyond its ends.

    Attributes:
        times: Frame times (K,) (s), increasing.
        ha: Capsule starts (K, M, 3) (m).
        hd: Capsule axes (K, M, 3) (m).
        hr: Capsule radii (M,) (m).
    """

    times: np.ndarray
    ha: np.ndarray
    hd: np.ndarray
    hr: np.ndarray


class TimingGovernor(NamedTuple):
    """The governor's model (:class:`app.safety.governor.GovernorModel`) as the kernel reads it.

    Attributes:
        separation: ``(s0_m, t_reaction_s, stop_decel_mps2, human_speed_max_mps, human_accel_mps2)``.
        law: The speed-scaling law's ``(T_r + T_s, C + Z_d + Z_r, T_r + T_s / 2)``, or empty (none).
        scales: The grid of scales of the envelope.
        env_u: The instants of a brake (fractions of it).
        misc: ``(tracking_margin_m, speed_window_s, sensing_age_s, near_band_m, speed_noise_mps, min_scale,
            brake_decel_mps2, brake_joint_decel, ahead, toward)``: ``ahead``, the governor's look-ahead in
            sample points; ``toward`` 1 where the governor takes the parts' speeds toward the person, 0
            where it takes their whole speeds.
        caps: (M,) each person capsule's permissible contact speed (m/s; -1: no contact permitted): power
            and force limiting (:func:`app.safety.pfl.pfl_levels`).
        levels: (K,) the distinct values of ``caps`` and -1, ascending.
        floors: (M,) each capsule's least approach speed (m/s): ISO 13855's (the measured one where faster).
    """

    separation: np.ndarray
    law: np.ndarray
    scales: np.ndarray
    env_u: np.ndarray
    misc: np.ndarray
    caps: np.ndarray
    levels: np.ndarray
    floors: np.ndarray


@jit
def _person_distances(
    person: TimingPerson, t: float, ra: np.ndarray, rd: np.ndarray, rr: np.ndarray, out: np.ndarray
) -> None:
    """Signed distances (L, M) of the robot capsules ``ra``, ``rd`` (L, 3) to the person at time ``t``."""
    times = person.times
    k = times.shape[0]
    i0, i1, w = 0, 0, 0.0
    if k > 1:
        tc = min(max(t, times[0]), times[k - 1])
        i1 = int(np.searchsorted(times, tc, side="right"))
        i1 = min(max(i1, 1), k - 1)
        i0 = i1 - 1
        w = (tc - times[i0]) / (times[i1] - times[i0])
    ha, hd, hr = person.ha, person.hd, person.hr
    for m in range(hr.shape[0]):
        ax = ha[i0, m, 0] * (1.0 - w) + ha[i1, m, 0] * w
        ay = ha[i0, m, 1] * (1.0 - w) + ha[i1, m, 1] * w
        az = ha[i0, m, 2] * (1.0 - w) + ha[i1, m, 2] * w
        dx = hd[i0, m, 0] * (1.0 - w) + hd[i1, m, 0] * w
        dy = hd[i0, m, 1] * (1.0 - w) + hd[i1, m, 1] * w
        dz = hd[i0, m, 2] * (1.0 - w) + hd[i1, m, 2] * w
        for i in range(rr.shape[0]):
            s = _seg_dist(
                ra[i, 0], ra[i, 1], ra[i, 2], rd[i, 0], rd[i, 1], rd[i, 2], ax, ay, az, dx, dy, dz
            )  # fmt: skip
            out[i, m] = s - rr[i] - hr[m]


@jit
def toward_steps(i: int, n: int, ahead: int) -> np.ndarray:
    """The sample points ahead of point ``i`` (of ``0..n``) at which the walk measures each part's closing on
    the person: the next one, half the governor's look-ahead (``ahead`` points) and all of it."""
    out = np.empty(3, dtype=np.int64)
    out[0] = min(i + 1, n)
    out[1] = min(i + max(ahead // 2, 1), n)
    out[2] = min(i + max(ahead, 1), n)
    return out


@jit
def predicted_scales_kernel(
    path: TimingPath, person: TimingPerson, gov: TimingGovernor, t0: float
) -> tuple[np.ndarray, np.ndarray]:
    """The wall times (N + 1,) at which the robot reaches each point of ``path`` (the first is ``t0``) and the
    scale (N,) predicted for each move to the next point (see the module docstring).

    Each part's speed toward the person at point ``i`` is, like the supervisor's
    (:func:`app.safety.governor.closing_bound`), the largest average rate at which the path closes its
    separation from the person held where the forecast has them then, to the points :func:`toward_steps`
    names (negative: moving away), at most its whole speed."""
    margin, window, age, band, noise, min_scale, decel, jdecel = (
        gov.misc[0], gov.misc[1], gov.misc[2], gov.misc[3], gov.misc[4], gov.misc[5], gov.misc[6], gov.misc[7]
    )  # fmt: skip
    v_max_h, accel = gov.separation[3], gov.separation[4]
    tau = path.tau
    n = tau.shape[0] - 1
    n_parts = path.rr.shape[0]
    n_caps = person.hr.shape[0]
    t = np.empty(n + 1)
    scales = np.empty(n)
    t[0] = t0
    d0 = np.empty((n_parts, n_caps))
    d1 = np.empty((n_parts, n_caps))
    sep_lb = np.empty(n_parts)
    v1 = np.empty(n_parts)
    vh0 = np.empty(n_parts)
    vp = np.empty(n_parts)
    toward = np.empty(n_parts)
    sep_now = np.empty(n_parts)
    d2 = np.empty((n_parts, n_caps))
    extra = np.empty((n_parts, gov.levels.shape[0]))
    v_lv = np.empty((n_parts, gov.levels.shape[0]))
    v_pairs = np.empty((n_parts, n_caps))
    ahead = int(gov.misc[8])
    half = 0.5 * window
    for i in range(n):
        vtop = 0.0
        for p in range(n_parts):
            vp[p] = max(path.v[i, p], path.v[i + 1, p])
            vtop = max(vtop, vp[p])
        s = 1.0
        if vtop > 1e-4:
            _person_distances(person, t[i], path.ra[i], path.rd[i], path.rr, d0)
            _person_distances(person, t[i] - window, path.ra[i], path.rd[i], path.rr, d1)
            for p in range(n_parts):
                sep = d0[p, 0]
                for m in range(1, n_caps):
                    sep = min(sep, d0[p, m])
                v_h = 0.0  # the directed approach (app.safety.governor.directed_approach)
                for m in range(n_caps):
                    v_m = max(max(d1[p, m] - d0[p, m], 0.0) / max(window, 1e-6) + noise, gov.floors[m])
                    v_pairs[p, m] = v_m
                    if d0[p, m] <= sep + band:
                        v_h = max(v_h, v_m)
                vh0[p] = v_h
                sep_now[p] = sep
                toward[p] = -np.inf if gov.misc[9] > 0.0 else vp[p]
                x0, _ = approach(vh0[p], half, v_max_h, accel)
                x1, v_1 = approach(vh0[p], half + age, v_max_h, accel)
                sep_lb[p] = sep - margin - (x1 - x0)
                v1[p] = v_1
            steps = toward_steps(i, n, ahead)
            for k in range(steps.shape[0] if gov.misc[9] > 0.0 else 0):
                j = steps[k]
                if j <= i or (k > 0 and j == steps[k - 1]):
                    continue
                _person_distances(person, t[i], path.ra[j], path.rd[j], path.rr, d2)
                for p in range(n_parts):
                    sep_j = d2[p, 0]
                    for m in range(1, n_caps):
                        sep_j = min(sep_j, d2[p, m])
                    toward[p] = max(toward[p], (sep_now[p] - sep_j) / max(tau[j] - tau[i], 1e-12))
            for p in range(n_parts):
                toward[p] = min(toward[p], vp[p]) if toward[p] > -np.inf else 0.0
                if toward[p] > 0.0:  # a closing part counts at its whole speed, as the governor counts it
                    toward[p] = vp[p]
            w_top = max(path.w[i], path.w[i + 1])
            rate = np.inf
            if vtop > 1e-9:
                rate = decel / vtop
            if w_top > 1e-9:
                rate = min(rate, jdecel / w_top)
            pfl_extra(d0, v_pairs, gov.caps, gov.levels, band, extra, v_lv)
            if accel > 0.0:  # a person who may speed up: the part's grown worst case alone
                v_lv[:, :] = np.inf
            s = max_scale(
                sep_lb,
                v1,
                toward,
                rate,
                0.0,
                1.0,
                gov.scales,
                gov.env_u,
                gov.separation,
                gov.levels,
                extra,
                v_lv,
            )
            if gov.law.shape[0] > 0:
                s = min(s, max(law_scale(sep_lb, toward, vh0, gov.law, gov.levels, extra, v_lv), 0.0))
        scales[i] = max(s, min_scale)
        t[i + 1] = t[i] + (tau[i + 1] - tau[i]) / scales[i]
    return t, scales
