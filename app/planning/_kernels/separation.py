"""The planner's time-sampled separation checks, compiled: samples (:func:`sample_separation_ok`) and whole
moves with their hold (:func:`moves_separation_ok`) against a forecast person, each in one pass with a
broad phase of bounding spheres and boxes before the exact capsule distances."""

from __future__ import annotations

import math

import numpy as np

from app.planning._kernels.arrays import (
    CapsuleBounds,
    MotionModel,
    Moves,
    PersonCapsules,
    PersonForecast,
    Requirement,
    RobotArrays,
)
from app.planning._kernels.base import _interp, _jit, _pose_index, _searchsorted_left, _seg_dist
from app.planning._kernels.geometry import _person_capsules, _segments_one
from app.planning._kernels.profiles import _profile3, _profile_sample

__all__ = ["moves_separation_ok", "sample_separation_ok"]


@_jit
def _too_close(
    SA: np.ndarray,
    SD: np.ndarray,
    near: np.ndarray,
    ra: np.ndarray,
    C: np.ndarray,
    rh: np.ndarray,
    req: float,
    SB: np.ndarray,
    soft: np.ndarray,
    req_soft: float,
) -> bool:
    """Whether some robot capsule flagged ``near`` (segments ``SA``/``SD`` (L, 3)) comes closer than ``req``
    to some person capsule ``C`` (M, 6), or than ``req_soft`` to one flagged ``soft`` (M,) (checked for
    contact only: :attr:`PersonCapsules.soft`; 2.0: not checked at all, the trajectory check's capsules whose
    contact the robot's speed keeps permissible) (a NaN distance counts as too close). ``SB`` (L, 4): scratch.

    A pair whose bounding spheres (centre of the axis, half its length plus the radius) are at least
    ``req`` apart cannot be too close (the surface distance is never below the spheres' gap) and is not
    computed."""
    L = SA.shape[0]
    for i in range(L):
        if near[i]:
            h2 = 0.0
            for j in range(3):
                SB[i, j] = SA[i, j] + 0.5 * SD[i, j]
                h2 += SD[i, j] * SD[i, j]
            SB[i, 3] = 0.5 * math.sqrt(h2) + ra[i]
    for m in range(C.shape[0]):
        if soft[m] > 1.5:
            continue  # a contact here is within the region's permissible speed: no clearance asked
        cx = C[m, 0] + 0.5 * C[m, 3]
        cy = C[m, 1] + 0.5 * C[m, 4]
        cz = C[m, 2] + 0.5 * C[m, 5]
        rm = 0.5 * math.sqrt(C[m, 3] * C[m, 3] + C[m, 4] * C[m, 4] + C[m, 5] * C[m, 5]) + rh[m]
        rq = req_soft if soft[m] > 0.0 else req
        for i in range(L):
            if not near[i]:
                continue
            lim = rq + SB[i, 3] + rm
            dx = SB[i, 0] - cx
            dy = SB[i, 1] - cy
            dz = SB[i, 2] - cz
            if lim > 0.0 and dx * dx + dy * dy + dz * dz >= lim * lim:
                continue  # the bounding spheres are far enough apart (a NaN never skips)
            s = _seg_dist(
                SA[i, 0], SA[i, 1], SA[i, 2], SD[i, 0], SD[i, 1], SD[i, 2],
                C[m, 0], C[m, 1], C[m, 2], C[m, 3], C[m, 4], C[m, 5],
            )  # fmt: skip
            if not (s - (ra[i] + rh[m]) >= rq):
                return True
    return False


@_jit
def _pose_at(
    ts: float,
    times: np.ndarray,
    joints: np.ndarray,
    djoints: np.ndarray,
    dtimes: np.ndarray,
    pose: np.ndarray,
) -> None:
    """The forecast pose (J, 3) at time ``ts`` into ``pose`` (:meth:`HumanForecast.poses_at`'s linear
    interpolation between the samples ``times`` (H,), ``joints`` (H, J, 3); the ends held)."""
    H = times.shape[0]
    J = joints.shape[1]
    if H == 1:
        for jj in range(J):
            for j in range(3):
                pose[jj, j] = joints[0, jj, j]
        return
    tc = min(max(ts, times[0]), times[H - 1])
    i0 = min(_pose_index(times, tc), H - 1) - 1
    w = (tc - times[i0]) / dtimes[i0]
    for jj in range(J):
        for j in range(3):
            pose[jj, j] = joints[i0, jj, j] + w * djoints[i0, jj, j]


@_jit
def _sphere_gaps_near(
    cen: np.ndarray, rad: np.ndarray, lo: np.ndarray, hi: np.ndarray, req: float, near: np.ndarray
) -> bool:
    """Per robot capsule (spheres ``cen`` (L, 3), ``rad`` (L,)): whether its sphere comes within ``req`` of
    the box ``lo``/``hi`` (3+,) (into ``near`` (L,)); returns whether any does."""
    any_near = False
    for l in range(cen.shape[0]):  # noqa: E741
        g2 = 0.0
        for j in range(3):
            c = cen[l, j]
            g = max(max(lo[j] - c, c - hi[j]), 0.0)
            g2 += g * g
        near[l] = math.sqrt(g2) - rad[l] < req
        any_near = any_near or near[l]
    return any_near


@_jit
def sample_separation_ok(
    q: np.ndarray,
    t: np.ndarray,
    req: np.ndarray,
    cen: np.ndarray,
    rad: np.ndarray,
    use_spheres: bool,
    groups: np.ndarray,
    n_groups: int,
    forecast: PersonForecast,
    robot: RobotArrays,
    person: PersonCapsules,
    prm: np.ndarray,
) -> tuple[np.ndarray, int]:
    """The planner's sample check (:meth:`app.planning.search.separation._Separation.check`) in one pass.

    Sample ``s`` (configuration ``q[s]`` (6,)) passes when for every time offset ``o`` its surface distance
    to the forecast pose at ``t[o, s]`` is at least ``req[o, s]`` (m). Broad phase (``use_spheres``): a
    sphere (``cen[s]`` (L, 3), ``rad[s]`` (L,)) per robot capsule against the box ``lo_pair``/``hi_pair``
    around the person over the forecast interval of the sample's time; capsules far from it are not
    computed, and a sample with none near passes without forward kinematics. The pose at ``t`` is the
    forecast's linear interpolation (``times`` (H,), ``joints`` (H, J, 3), ``djoints``/``dtimes`` its
    differences; the ends held). With ``n_groups > 0`` the samples of one group (``groups`` (S,)) matter
    only together: once one fails, the group's remaining samples are reported failing without computing.

    Capsules flagged :attr:`PersonCapsules.soft` need only :func:`_required_soft` (``prm``:
    :attr:`Requirement.params`).

    Returns ``(ok (S,) bool, exact)``: the verdicts and how many (sample, offset) pairs needed the exact
    distance.
    """
    forecast = PersonForecast(*forecast)
    robot = RobotArrays(*robot)
    person = PersonCapsules(*person)
    times, joints, djoints, dtimes = forecast.times, forecast.joints, forecast.djoints, forecast.dtimes
    lo_pair, hi_pair = forecast.lo_pair, forecast.hi_pair
    ra = robot.ra
    ia, ib, rh, soft = person.ia, person.ib, person.rh, person.soft
    S = q.shape[0]
    n_off = t.shape[0]
    L = ra.shape[0]
    M = ia.shape[0]
    J = joints.shape[1]
    n_pair = lo_pair.shape[0]
    ok = np.ones(S, dtype=np.bool_)
    failed = np.zeros(max(n_groups, 1), dtype=np.bool_)
    near = np.ones(L, dtype=np.bool_)
    X = np.empty((7, 3))
    Y = np.empty((7, 3))
    Z = np.empty((7, 3))
    P = np.empty((7, 3))
    SA = np.empty((L, 3))
    SD = np.empty((L, 3))
    SB = np.empty((L, 4))
    pose = np.empty((1, J, 3))
    C = np.empty((M, 6))
    exact = 0
    for s in range(S):
        if n_groups > 0 and failed[groups[s]]:
            ok[s] = False
            continue
        have_segments = False
        for o in range(n_off):
            ts = t[o, s]
            rq = req[o, s]
            if use_spheres:
                i = min(max(_pose_index(times, ts) - 1, 0), n_pair - 1)
                if not _sphere_gaps_near(cen[s], rad[s], lo_pair[i], hi_pair[i], rq, near):
                    continue
            if not have_segments:
                _segments_one(q, s, robot, X, Y, Z, P, SA, SD)
                have_segments = True
            _pose_at(ts, times, joints, djoints, dtimes, pose[0])
            _person_capsules(pose, 0, ia, ib, C)
            exact += 1
            if _too_close(SA, SD, near, ra, C, rh, rq, SB, soft, min(_required_soft(prm), rq)):
                ok[s] = False
                if n_groups > 0:
                    failed[groups[s]] = True
                break
    return ok, exact


@_jit
def _window_box(
    t0: float,
    t1: float,
    times: np.ndarray,
    lo_tab: np.ndarray,
    hi_tab: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
) -> None:
    """The box (``lo`` (3,), ``hi`` (4,): upper corner and the largest margin) that contains the person over
    ``[t0, t1]``, from the sparse table of unions ``lo_tab`` (K, H, 3) / ``hi_tab`` (K, H, 4) (level k holds
    the unions over the index ranges [i, i + 2^k));
    :meth:`app.planning.search.separation._Separation._boxes`."""
    H = times.shape[0]
    i0 = min(max(_pose_index(times, t0) - 1, 0), H - 1)
    i1 = max(min(_searchsorted_left(times, t1), H - 1), i0)
    n = i1 - i0 + 1
    k = 0
    while (2 << k) <= n:
        k += 1
    b = i1 - (1 << k) + 1
    for j in range(3):
        lo[j] = min(lo_tab[k, i0, j], lo_tab[k, b, j])
    for j in range(4):
        hi[j] = max(hi_tab[k, i0, j], hi_tab[k, b, j])


@_jit
def _margin_at(t: float, times: np.ndarray, margins: np.ndarray, growth: float, cap: float) -> float:
    """The forecast's margin (m) at time ``t``
    (:meth:`app.planning.search.separation._Separation._margins`)."""
    m = _interp(t, times, margins)
    if growth > 0.0:
        m = min(m + growth * max(t - times[times.shape[0] - 1], 0.0), cap)
    return m


@_jit
def _robot_distance(v: float, w: float, t_r: float, decel: float, joint_decel: float, delay: float) -> float:
    """``S_r + S_s`` (m) of :func:`app.safety.ssm.forecast_clearance`: a robot whose fastest point moves at
    ``v`` (m/s) and fastest joint at ``w`` (rad/s) goes ``v T_r`` before it brakes and ``S_s`` of the
    stopping model (:class:`app.safety.stopping.StoppingModel`: ``decel``, ``joint_decel``, ``delay``)
    while it stops."""
    v = max(v, 0.0)
    brake = max(v / decel, max(w, 0.0) / joint_decel)
    return v * t_r + v * (delay + 0.5 * brake)


@_jit
def _required(v: float, w: float, margin: float, prm: np.ndarray) -> float:
    """:func:`app.safety.ssm.forecast_clearance` for a robot whose fastest point moves at ``v`` (m/s) and
    fastest joint at ``w`` (rad/s) + the extra distance (+ the SSM-aware table where ``prm`` carries one:
    :meth:`app.planning.search._Separation.ssm_extra`), capped at the floor (m); ``prm``:
    :attr:`Requirement.params`."""
    req = _robot_distance(v, w, prm[2], prm[8], prm[9], prm[10]) + prm[3] + prm[4] + max(prm[5], margin)
    n = prm.shape[0]
    if n > 13:  # SSM-aware: the governor's extra clearance at speed v, tabulated from prm[12] every prm[11]
        x = max(v, 0.0) / prm[11]
        i = int(x)
        if i >= n - 13:
            req += prm[n - 1]
        else:
            req += prm[12 + i] + (x - i) * (prm[13 + i] - prm[12 + i])
    return min(req + prm[6], prm[7])


@_jit
def _required_soft(prm: np.ndarray) -> float:
    """The separation (m) asked of a capsule checked for contact only (:attr:`PersonCapsules.soft`): the
    sensing uncertainty ``Z_d`` + the extra distance, capped at the floor (``prm``:
    :attr:`Requirement.params`): no contact with the person where the forecast expects them. The forecast's
    margin (where the person may be instead) does not enter: a region that admits contact is no obstacle
    where it only may be, the governor holds the robot to its permissible speed there."""
    return min(prm[5] + prm[6], prm[7])


@_jit
def moves_separation_ok(
    moves: Moves,
    tables: CapsuleBounds,
    motion: MotionModel,
    hold_s: float,
    requirement: Requirement,
    forecast: PersonForecast,
    robot: RobotArrays,
    person: PersonCapsules,
) -> tuple[np.ndarray, int, int]:
    """The planner's move check (:meth:`app.planning.search.Planner._moves_ok`) in one pass.

    Move ``k`` (of ``moves``) runs straight in joint space from ``q_a[k]`` to ``target[k]`` (6,), departing
    at ``t_dep[k]`` and lasting ``h[k]`` s; its path-speed profile
    (:func:`app.planning.search.profiles._profile_samples`) has entry speed ``u0``, path length ``L``, cruise
    speed ``f`` and ends at rest where ``end_rest``; where ``hold[k]`` the robot must then stand at the
    target for ``hold_s``. Robot geometry at the start: capsule end points ``pts_a`` (M, P, 3) and bounding
    spheres ``cen_a`` (M, L, 3) / ``rad_a`` (M, L); at the target: row ``rows[k]`` of ``tables``. In
    ``motion``, ``lever`` (6,) bounds how far a joint's unit turn moves any point, ``moved_by`` (L,) is the
    last joint that moves each capsule (so ``travel`` = how far the joints can carry it), and the robot
    speed of a sample is its path speed times ``speed_factor`` x the largest chord per unit of path (as
    :meth:`Planner._move_prep`).

    Stage 0: a move whose capsules (the mid spheres grown by the travel) stay beyond the requirement of the
    box around the person over the move's whole time window passes. Otherwise its samples (every
    ``sample_dt`` of the move, its end, then the hold) are checked like :func:`sample_separation_ok` (each at
    every time ``requirement.offsets`` (n_off,)), and the move fails at its first sample that is too close.
    ``requirement.params``: see :class:`Requirement`; the forecast's ``margins`` (H,) and the sparse table
    ``lo_tab``/``hi_tab`` of :func:`_window_box`; the rest as in :func:`sample_separation_ok`.

    Returns ``(ok (M,) bool, samples, exact)``: the verdicts, the (sample, offset) pairs looked at and those
    that needed the exact distance.
    """
    moves = Moves(*moves)
    tables = CapsuleBounds(*tables)
    motion = MotionModel(*motion)
    requirement = Requirement(*requirement)
    forecast = PersonForecast(*forecast)
    robot = RobotArrays(*robot)
    person = PersonCapsules(*person)
    q_a, target, pts_a, cen_a, rad_a = moves.q_a, moves.target, moves.pts_a, moves.cen_a, moves.rad_a
    rows, t_dep, h, u0, Lp, f = moves.rows, moves.t_dep, moves.h, moves.u0, moves.L, moves.f
    end_rest, hold = moves.end_rest, moves.hold
    pts_tab, cen_tab, rad_tab = tables.pts, tables.cen, tables.rad
    lever, moved_by = motion.lever, motion.moved_by
    speed_factor, A, sample_dt = motion.speed_factor, motion.accel, motion.sample_dt
    offsets, prm, jw = requirement.offsets, requirement.params, requirement.joint_weights
    times, joints, djoints, dtimes = forecast.times, forecast.joints, forecast.djoints, forecast.dtimes
    lo_pair, hi_pair = forecast.lo_pair, forecast.hi_pair
    margins, lo_tab, hi_tab = forecast.margins, forecast.lo_tab, forecast.hi_tab
    ra = robot.ra
    ia, ib, rh, soft = person.ia, person.ib, person.rh, person.soft
    M = q_a.shape[0]
    L = ra.shape[0]
    NP = pts_a.shape[1]
    NC = ia.shape[0]
    J = joints.shape[1]
    n_pair = lo_pair.shape[0]
    n_off = offsets.shape[0]
    growth = prm[0]
    cap = prm[1]
    lo_off = offsets[0]
    hi_off = offsets[0]
    for o in range(n_off):
        lo_off = min(lo_off, offsets[o])
        hi_off = max(hi_off, offsets[o])
    n_hold = max(math.ceil(hold_s / sample_dt - 1e-9), 0)
    hold_step = hold_s / max(n_hold, 1)
    ok = np.ones(M, dtype=np.bool_)
    near = np.ones(L, dtype=np.bool_)
    cen = np.empty((L, 3))
    rad = np.empty(L)
    travel = np.empty(L)
    cum = np.empty(7)
    dq = np.empty(6)
    lo = np.empty(3)
    hi = np.empty(4)
    qbuf = np.empty((1, 6))
    X = np.empty((7, 3))
    Y = np.empty((7, 3))
    Z = np.empty((7, 3))
    P = np.empty((7, 3))
    SA = np.empty((L, 3))
    SD = np.empty((L, 3))
    SB = np.empty((L, 4))
    pose = np.empty((1, J, 3))
    C = np.empty((NC, 6))
    n_samples = 0
    n_exact = 0
    for k in range(M):
        rb = rows[k]
        # how far the joints can carry each capsule, the largest chord, the profile
        cum[0] = 0.0
        for j in range(6):
            dq[j] = target[k, j] - q_a[k, j]
            cum[j + 1] = cum[j] + abs(dq[j]) * lever[j]
        for l in range(L):  # noqa: E741
            travel[l] = cum[moved_by[l]]
        chord = 0.0
        for p in range(NP):
            d0 = pts_tab[rb, p, 0] - pts_a[k, p, 0]
            d1 = pts_tab[rb, p, 1] - pts_a[k, p, 1]
            d2 = pts_tab[rb, p, 2] - pts_a[k, p, 2]
            chord = max(chord, math.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        Lk = Lp[k]
        dur, _, peak = _profile3(u0[k], Lk, f[k], A, end_rest[k])
        hk = h[k]
        clock = dur / max(hk, 1e-12) if hk > 0 else 1.0  # profile seconds per real second
        kv = speed_factor * chord * clock / max(Lk, 1e-12) if Lk > 1e-12 else 0.0
        # the fastest joint's speed per unit of path speed (a straight joint move: exact)
        dq_max = 0.0
        for j in range(6):
            dq_max = max(dq_max, abs(dq[j]) * jw[j])
        kw = dq_max * clock / max(Lk, 1e-12) if Lk > 1e-12 else 0.0
        # stage 0: the whole move (and its hold) against the person's box over its time window
        t0 = t_dep[k] + lo_off
        t1 = t_dep[k] + hk + (hold_s if hold[k] else 0.0) + hi_off
        _window_box(t0, t1, times, lo_tab, hi_tab, lo, hi)
        m_hi = max(
            hi[3],
            max(_margin_at(t0, times, margins, growth, cap), _margin_at(t1, times, margins, growth, cap)),
        )
        rq = _required(kv * peak, kw * peak, m_hi, prm)
        for l in range(L):  # noqa: E741
            for j in range(3):
                cen[l, j] = 0.5 * (cen_a[k, l, j] + cen_tab[rb, l, j])
            rad[l] = 0.5 * (rad_a[k, l] + rad_tab[rb, l] + travel[l])
        if not _sphere_gaps_near(cen, rad, lo, hi, rq, near):
            continue
        # the samples: every sample_dt of the move (its end included), then the hold
        n = max(math.ceil(hk / sample_dt - 1e-9), 1)
        tot = n + (n_hold if hold[k] else 0)
        for i in range(1, tot + 1):
            in_move = i <= n
            tau = (i / n if in_move else 1.0) * hk
            frac, speed = _profile_sample(
                tau * clock, (i - 1 if in_move else n) / n * hk * clock, u0[k], Lk, dur, f[k], A, end_rest[k]
            )
            if not in_move:
                frac = 1.0
            for j in range(6):
                qbuf[0, j] = q_a[k, j] + frac * dq[j]
            ts = t_dep[k] + tau + (0.0 if in_move else (i - n) * hold_step)
            v = kv * speed if in_move else 0.0
            w = kw * speed if in_move else 0.0
            # each capsule lies within its start sphere grown by frac * travel and its end sphere grown by
            # (1 - frac) * travel: the smaller of the two
            for l in range(L):  # noqa: E741
                r_a = rad_a[k, l] + frac * travel[l]
                r_b = rad_tab[rb, l] + (1.0 - frac) * travel[l]
                if r_a <= r_b:
                    rad[l] = r_a
                    for j in range(3):
                        cen[l, j] = cen_a[k, l, j]
                else:
                    rad[l] = r_b
                    for j in range(3):
                        cen[l, j] = cen_tab[rb, l, j]
            have_segments = False
            for o in range(n_off):
                to = ts + offsets[o]
                rq = _required(v, w, _margin_at(to, times, margins, growth, cap), prm)
                n_samples += 1
                ip = min(max(_pose_index(times, to) - 1, 0), n_pair - 1)
                if not _sphere_gaps_near(cen, rad, lo_pair[ip], hi_pair[ip], rq, near):
                    continue
                if not have_segments:
                    _segments_one(qbuf, 0, robot, X, Y, Z, P, SA, SD)
                    have_segments = True
                _pose_at(to, times, joints, djoints, dtimes, pose[0])
                _person_capsules(pose, 0, ia, ib, C)
                n_exact += 1
                if _too_close(SA, SD, near, ra, C, rh, rq, SB, soft, min(_required_soft(prm), rq)):
                    ok[k] = False
                    break
            if not ok[k]:
                break
    return ok, n_samples, n_exact
