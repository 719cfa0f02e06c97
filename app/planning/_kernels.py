"""Compiled (numba) kernels for the geometric hot paths: UR5e forward kinematics to capsule segments,
segment-segment distances, robot-person minimum distances, and the planner's time-sampled separation checks.

The NumPy implementations in :mod:`app.planning.kinematics` and :mod:`app.planning.collision` stay the
reference (the tests compare against them); the public functions route through these kernels.

Numerics: every kernel is ``fastmath=False`` float64. The forward kinematics performs the same operations in
the same order as the component-major NumPy chain. The closest points of two segments follow the same three
clamped steps as :func:`app.planning.collision._closest_sq` (Ericson, Real-Time Collision Detection, 5.1.9),
but the distance is then taken from the closest points themselves (``|r + s d1 - t d2|``) instead of the
expansion in dot products: it agrees with the NumPy reference to round-off (below 1e-12 m) wherever the axes
are more than a micrometre apart, and is exact to round-off where they touch (the expansion's square root
of a cancelled difference is off by up to a few 1e-8 m there).

Calling convention: arrays are C-contiguous float64 (index arrays int64); the callers make sure of it so that
each kernel compiles for one signature only. Compiled code is cached next to this file (``cache=True``);
where that directory is not writable numba falls back to its per-user cache, and where no cache location can
be written at all the kernels are compiled in memory on first use (a warning is logged once).

Layouts: robot segments are *component-major* ``(L, 3, B)`` (starts ``a`` and directions ``d = end -
start``), as :meth:`app.planning.collision.CollisionModel.robot_segments` returns them; person poses are
``(H, J, 3)`` and a person capsule ``m`` runs from joint ``ia[m]`` to joint ``ib[m]``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from app.jit import jit

__all__ = [
    "align_rows",
    "as_bool",
    "as_f64",
    "as_i64",
    "chain_frames",
    "cross_min_distance",
    "moves_separation_ok",
    "pair_distances",
    "paired_min_distance",
    "robot_segments",
    "sample_separation_ok",
    "segment_distances",
    "self_distances",
    "trajectory_first_violation",
]

logger = logging.getLogger(__name__)

_TINY = 1e-18  # m^4: as app.planning.collision._TINY (parallel segments, points)
_NL = 9  # robot capsules (app.planning.collision.ROBOT_LINKS)


def _jit(fn: Callable[..., Any]) -> Any:
    """:func:`app.jit.jit` with the options of every planning kernel."""
    return jit(fn, fastmath=False, nogil=True)


def as_f64(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable float64 array (a copy only where needed): the one array type the
    kernels are compiled for (numba compiles read-only and strided arrays separately)."""
    if isinstance(x, np.ndarray) and x.dtype == np.float64 and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.float64, order="C")


def as_bool(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable bool array (see :func:`as_f64`)."""
    if isinstance(x, np.ndarray) and x.dtype == np.bool_ and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.bool_, order="C")


def as_i64(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous, writeable int64 array (see :func:`as_f64`)."""
    if isinstance(x, np.ndarray) and x.dtype == np.int64 and x.flags.c_contiguous and x.flags.writeable:
        return x
    return np.array(x, dtype=np.int64, order="C")


# ------------------------------------------------------------------------------------------ scalar helpers


@_jit
def _clip01(x: float) -> float:
    if x < 0.0:
        return 0.0
    if x > 1.0:
        return 1.0
    return x  # NaN stays NaN (as np.maximum / np.minimum)


@_jit
def _seg_dist(
    p1x: float,
    p1y: float,
    p1z: float,
    d1x: float,
    d1y: float,
    d1z: float,
    p2x: float,
    p2y: float,
    p2z: float,
    d2x: float,
    d2y: float,
    d2z: float,
) -> float:
    """Distance between segments p1 + s d1 and p2 + t d2 (s, t in [0, 1]), m."""
    rx = p1x - p2x
    ry = p1y - p2y
    rz = p1z - p2z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    b = d1x * d2x + d1y * d2y + d1z * d2z
    c = d1x * rx + d1y * ry + d1z * rz
    f = d2x * rx + d2y * ry + d2z * rz
    inv_a = 1.0 / a if a > _TINY else 0.0
    inv_e = 1.0 / e if e > _TINY else 0.0
    den = a * e - b * b
    if den < _TINY:
        den = _TINY
    s = _clip01((b * f - c * e) / den)
    t = _clip01((b * s + f) * inv_e)
    s = _clip01((b * t - c) * inv_a)
    dx = rx + s * d1x - t * d2x
    dy = ry + s * d1y - t * d2y
    dz = rz + s * d1z - t * d2z
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@_jit
def _nan_min(best: float, d: float) -> float:
    """min(best, d) that keeps a NaN once one appears (as ndarray.min)."""
    if d < best or d != d:
        return d
    return best


# ------------------------------------------------------------------------------------ forward kinematics


@_jit
def _chain_one(
    q: np.ndarray,
    k: int,
    T_base: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    X: np.ndarray,
    Y: np.ndarray,
    Z: np.ndarray,
    P: np.ndarray,
) -> None:
    """World axes and origins (7, 3) each of DH frames 0..6 for configuration ``q[k]`` (component order of
    :meth:`app.planning.kinematics.UR5e._chain`)."""
    x0, x1, x2 = T_base[0, 0], T_base[1, 0], T_base[2, 0]
    y0, y1, y2 = T_base[0, 1], T_base[1, 1], T_base[2, 1]
    z0, z1, z2 = T_base[0, 2], T_base[1, 2], T_base[2, 2]
    p0, p1, p2 = T_base[0, 3], T_base[1, 3], T_base[2, 3]
    X[0, 0], X[0, 1], X[0, 2] = x0, x1, x2
    Y[0, 0], Y[0, 1], Y[0, 2] = y0, y1, y2
    Z[0, 0], Z[0, 1], Z[0, 2] = z0, z1, z2
    P[0, 0], P[0, 1], P[0, 2] = p0, p1, p2
    for i in range(6):
        c = math.cos(q[k, i])
        s = math.sin(q[k, i])
        # R_i = Rz(q_i) Rx(alpha_i): the parent axes turned about z ...
        nx0 = c * x0 + s * y0
        nx1 = c * x1 + s * y1
        nx2 = c * x2 + s * y2
        ny0 = c * y0 - s * x0
        ny1 = c * y1 - s * x1
        ny2 = c * y2 - s * x2
        # ... the origin: d along the parent z, then a along the new x ...
        di = dh_d[i]
        ai = dh_a[i]
        if di != 0.0:
            p0 = p0 + di * z0
            p1 = p1 + di * z1
            p2 = p2 + di * z2
        if ai != 0.0:
            p0 = p0 + ai * nx0
            p1 = p1 + ai * nx1
            p2 = p2 + ai * nx2
        # ... then the twist (0, pi/2, -pi/2) permutes y and z with signs.
        tw = twist[i]
        if tw > 0.0:
            y0, y1, y2 = z0, z1, z2
            z0, z1, z2 = -ny0, -ny1, -ny2
        elif tw < 0.0:
            y0, y1, y2 = -z0, -z1, -z2
            z0, z1, z2 = ny0, ny1, ny2
        else:
            y0, y1, y2 = ny0, ny1, ny2
        x0, x1, x2 = nx0, nx1, nx2
        X[i + 1, 0], X[i + 1, 1], X[i + 1, 2] = x0, x1, x2
        Y[i + 1, 0], Y[i + 1, 1], Y[i + 1, 2] = y0, y1, y2
        Z[i + 1, 0], Z[i + 1, 1], Z[i + 1, 2] = z0, z1, z2
        P[i + 1, 0], P[i + 1, 1], P[i + 1, 2] = p0, p1, p2


@_jit
def chain_frames(
    q: np.ndarray, T_base: np.ndarray, dh_d: np.ndarray, dh_a: np.ndarray, twist: np.ndarray
) -> np.ndarray:
    """World axes and origins of DH frames 0..6, ``(4, 7, 3, B)``: ``[x, y, z, p]`` component-major.

    Args:
        q: Joint angles (B, 6), rad.
        T_base: Pose (4, 4) of DH frame 0 in the world.
        dh_d, dh_a: DH offsets and lengths (6,), m.
        twist: Sign (6,) of each DH twist (+1: pi/2, -1: -pi/2, 0: none).
    """
    B = q.shape[0]
    out = np.empty((4, 7, 3, B))
    X = np.empty((7, 3))
    Y = np.empty((7, 3))
    Z = np.empty((7, 3))
    P = np.empty((7, 3))
    for k in range(B):
        _chain_one(q, k, T_base, dh_d, dh_a, twist, X, Y, Z, P)
        for f in range(7):
            for j in range(3):
                out[0, f, j, k] = X[f, j]
                out[1, f, j, k] = Y[f, j]
                out[2, f, j, k] = Z[f, j]
                out[3, f, j, k] = P[f, j]
    return out


@_jit
def _segments_one(
    q: np.ndarray,
    k: int,
    T_base: np.ndarray,
    t_tcp: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    off_shoulder: float,
    off_forearm: float,
    ext: np.ndarray,
    X: np.ndarray,
    Y: np.ndarray,
    Z: np.ndarray,
    P: np.ndarray,
    SA: np.ndarray,
    SD: np.ndarray,
) -> None:
    """Robot capsule segments (9, 3) starts ``SA`` and directions ``SD`` for configuration ``q[k]``, as
    :meth:`app.planning.collision.CollisionModel._robot_segments_cm` lays them out."""
    _chain_one(q, k, T_base, dh_d, dh_a, twist, X, Y, Z, P)
    for j in range(3):
        z1 = Z[1, j]
        e1 = P[1, j] + off_shoulder * z1  # shoulder end
        e2 = P[2, j] + off_shoulder * z1  # upper-arm end
        e3 = P[2, j] + off_forearm * z1  # elbow end
        e4 = P[3, j] + off_forearm * z1  # forearm end
        tcp = P[6, j] + t_tcp[0] * X[6, j] + t_tcp[1] * Y[6, j] + t_tcp[2] * Z[6, j]
        SA[0, j] = P[0, j]
        SD[0, j] = P[1, j] - P[0, j]
        SA[1, j] = P[1, j]
        SD[1, j] = e1 - P[1, j]
        SA[2, j] = e1
        SD[2, j] = e2 - e1
        SA[3, j] = e2
        SD[3, j] = e3 - e2
        SA[4, j] = e3
        SD[4, j] = e4 - e3
        SA[5, j] = e4
        SD[5, j] = P[4, j] - e4
        SA[6, j] = P[4, j]
        SD[6, j] = P[5, j] - P[4, j]
        SA[7, j] = P[5, j]
        SD[7, j] = P[6, j] - P[5, j]
        SA[8, j] = P[6, j]
        SD[8, j] = tcp - P[6, j]
    for l in range(_NL):  # noqa: E741  (the extensions, as CollisionModel._robot_segments_cm_numpy)
        f0 = ext[l, 0]
        s = 1.0 + f0 + ext[l, 1]
        for j in range(3):
            SA[l, j] -= f0 * SD[l, j]
            SD[l, j] *= s


@_jit
def robot_segments(
    q: np.ndarray,
    T_base: np.ndarray,
    t_tcp: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    off_shoulder: float,
    off_forearm: float,
    ext: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Robot capsule segments for configurations ``q`` (B, 6): starts and directions (9, 3, B) each (m).

    ``t_tcp`` (3,): the TCP in the flange frame (m); ``off_shoulder``/``off_forearm``: the offsets of the
    upper-arm and forearm centre lines along the shoulder axis (m); ``ext`` (9, 2): how far each segment
    reaches beyond its joint-axis start and end, as fractions of its length."""
    B = q.shape[0]
    a = np.empty((_NL, 3, B))
    d = np.empty((_NL, 3, B))
    X = np.empty((7, 3))
    Y = np.empty((7, 3))
    Z = np.empty((7, 3))
    P = np.empty((7, 3))
    SA = np.empty((_NL, 3))
    SD = np.empty((_NL, 3))
    for k in range(B):
        _segments_one(
            q, k, T_base, t_tcp, dh_d, dh_a, twist, off_shoulder, off_forearm, ext, X, Y, Z, P, SA, SD
        )
        for l in range(_NL):  # noqa: E741
            for j in range(3):
                a[l, j, k] = SA[l, j]
                d[l, j, k] = SD[l, j]
    return a, d


@_jit
def align_rows(q: np.ndarray, q_ref: np.ndarray, q_min: np.ndarray, q_max: np.ndarray) -> np.ndarray:
    """Every joint of ``q`` (n, 6) shifted by a multiple of 2 pi next to ``q_ref`` (n, 6) within the limits
    ``q_min``/``q_max`` (6,), else left as it is (:meth:`app.planning.search.Planner._align`)."""
    two_pi = 2.0 * math.pi
    inv = 1.0 / two_pi
    n = q.shape[0]
    out = np.empty((n, 6))
    for k in range(n):
        for j in range(6):
            x = q[k, j]
            y = x + two_pi * np.rint((q_ref[k, j] - x) * inv)
            if y > q_max[j]:
                y = y - two_pi
            if y < q_min[j]:
                y = y + two_pi
            out[k, j] = x if (y > q_max[j] or y < q_min[j]) else y
    return out


# ---------------------------------------------------------------------------------------------- distances


@_jit
def segment_distances(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Distances (N,) between segments [p1, q1] and [p2, q2], each (N, 3), m."""
    N = p1.shape[0]
    out = np.empty(N)
    for n in range(N):
        out[n] = _seg_dist(
            p1[n, 0],
            p1[n, 1],
            p1[n, 2],
            q1[n, 0] - p1[n, 0],
            q1[n, 1] - p1[n, 1],
            q1[n, 2] - p1[n, 2],
            p2[n, 0],
            p2[n, 1],
            p2[n, 2],
            q2[n, 0] - p2[n, 0],
            q2[n, 1] - p2[n, 1],
            q2[n, 2] - p2[n, 2],
        )
    return out


@_jit
def _person_capsules(joints: np.ndarray, h: int, ia: np.ndarray, ib: np.ndarray, C: np.ndarray) -> None:
    """Person capsules of pose ``joints[h]`` (J, 3) into ``C`` (M, 6): start and direction."""
    for m in range(ia.shape[0]):
        for j in range(3):
            s = joints[h, ia[m], j]
            C[m, j] = s
            C[m, 3 + j] = joints[h, ib[m], j] - s


@_jit
def self_distances(
    a: np.ndarray, d: np.ndarray, ra: np.ndarray, pi: np.ndarray, pj: np.ndarray
) -> np.ndarray:
    """Signed distances (B, P) between robot capsules ``pi[p]`` and ``pj[p]`` (segments (L, 3, B))."""
    B = a.shape[2]
    n = pi.shape[0]
    out = np.empty((B, n))
    for k in range(B):
        for p in range(n):
            i = pi[p]
            j = pj[p]
            s = _seg_dist(
                a[i, 0, k],
                a[i, 1, k],
                a[i, 2, k],
                d[i, 0, k],
                d[i, 1, k],
                d[i, 2, k],
                a[j, 0, k],
                a[j, 1, k],
                a[j, 2, k],
                d[j, 0, k],
                d[j, 1, k],
                d[j, 2, k],
            )
            out[k, p] = s - ra[i] - ra[j]
    return out


@_jit
def _min_pairs(R: np.ndarray, rr: np.ndarray, C: np.ndarray, rh: np.ndarray, SB: np.ndarray) -> float:
    """Min signed distance between the robot capsules ``R`` (n, 6: start, direction; radii ``rr`` (n,)) and
    the person capsules ``C`` (M, 6; radii ``rh`` (M,)); NaN if any distance is NaN. A pair whose bounding
    spheres are already at least the best distance so far apart is not computed (its distance is never
    below the spheres' gap). ``SB`` (n, 4): scratch."""
    n = R.shape[0]
    for i in range(n):
        h2 = 0.0
        for j in range(3):
            SB[i, j] = R[i, j] + 0.5 * R[i, 3 + j]
            h2 += R[i, 3 + j] * R[i, 3 + j]
        SB[i, 3] = 0.5 * math.sqrt(h2) + rr[i]
    best = np.inf
    for m in range(C.shape[0]):
        cx = C[m, 0] + 0.5 * C[m, 3]
        cy = C[m, 1] + 0.5 * C[m, 4]
        cz = C[m, 2] + 0.5 * C[m, 5]
        rm = 0.5 * math.sqrt(C[m, 3] * C[m, 3] + C[m, 4] * C[m, 4] + C[m, 5] * C[m, 5]) + rh[m]
        for i in range(n):
            lim = best + SB[i, 3] + rm
            dx = SB[i, 0] - cx
            dy = SB[i, 1] - cy
            dz = SB[i, 2] - cz
            if lim > 0.0 and dx * dx + dy * dy + dz * dz >= lim * lim:
                continue  # cannot beat the best so far (NaN never skips; +inf never skips)
            s = _seg_dist(
                R[i, 0], R[i, 1], R[i, 2], R[i, 3], R[i, 4], R[i, 5],
                C[m, 0], C[m, 1], C[m, 2], C[m, 3], C[m, 4], C[m, 5],
            )  # fmt: skip
            best = _nan_min(best, s - (rr[i] + rh[m]))
    return best


@_jit
def paired_min_distance(
    a: np.ndarray,
    d: np.ndarray,
    ra: np.ndarray,
    links: np.ndarray,
    joints: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> np.ndarray:
    """Min signed distance (K,) between robot configuration k (segments (L, 3, K), only the capsules
    ``links``) and person pose k (``joints`` (K, J, 3), capsules ``ia``/``ib``/``rh`` (M,)), m."""
    K = a.shape[2]
    M = ia.shape[0]
    nl = links.shape[0]
    out = np.empty(K)
    C = np.empty((M, 6))
    R = np.empty((nl, 6))
    rr = np.empty(nl)
    SB = np.empty((nl, 4))
    for i in range(nl):
        rr[i] = ra[links[i]]
    for k in range(K):
        _person_capsules(joints, k, ia, ib, C)
        for i in range(nl):
            l = links[i]  # noqa: E741
            for j in range(3):
                R[i, j] = a[l, j, k]
                R[i, 3 + j] = d[l, j, k]
        out[k] = _min_pairs(R, rr, C, rh, SB)
    return out


@_jit
def cross_min_distance(
    a: np.ndarray,
    d: np.ndarray,
    ra: np.ndarray,
    joints: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> np.ndarray:
    """Min signed distance (B, H) between every robot configuration (segments (L, 3, B)) and every person
    pose (``joints`` (H, J, 3)), m."""
    L = a.shape[0]
    B = a.shape[2]
    H = joints.shape[0]
    M = ia.shape[0]
    out = np.empty((B, H))
    C = np.empty((M, 6))
    R = np.empty((L, 6))
    SB = np.empty((L, 4))
    for h in range(H):
        _person_capsules(joints, h, ia, ib, C)
        for k in range(B):
            for i in range(L):
                for j in range(3):
                    R[i, j] = a[i, j, k]
                    R[i, 3 + j] = d[i, j, k]
            out[k, h] = _min_pairs(R, ra, C, rh, SB)
    return out


@_jit
def pair_distances(
    a: np.ndarray,
    d: np.ndarray,
    ra: np.ndarray,
    joints: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> np.ndarray:
    """Signed distance (P, L, M) of every robot capsule (one configuration: segments (L, 3, 1)) to every
    capsule of every person pose (``joints`` (P, J, 3)), m."""
    L = a.shape[0]
    P = joints.shape[0]
    M = ia.shape[0]
    out = np.empty((P, L, M))
    C = np.empty((M, 6))
    for p in range(P):
        _person_capsules(joints, p, ia, ib, C)
        for i in range(L):
            for m in range(M):
                s = _seg_dist(
                    a[i, 0, 0], a[i, 1, 0], a[i, 2, 0], d[i, 0, 0], d[i, 1, 0], d[i, 2, 0],
                    C[m, 0], C[m, 1], C[m, 2], C[m, 3], C[m, 4], C[m, 5],
                )  # fmt: skip
                out[p, i, m] = s - ra[i] - rh[m]
    return out


# --------------------------------------------------------------------------- planner: time-sampled checks


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
) -> bool:
    """Whether some robot capsule flagged ``near`` (segments ``SA``/``SD`` (L, 3)) comes closer than ``req``
    to some person capsule ``C`` (M, 6) (a NaN distance counts as too close). ``SB`` (L, 4): scratch.

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
        cx = C[m, 0] + 0.5 * C[m, 3]
        cy = C[m, 1] + 0.5 * C[m, 4]
        cz = C[m, 2] + 0.5 * C[m, 5]
        rm = 0.5 * math.sqrt(C[m, 3] * C[m, 3] + C[m, 4] * C[m, 4] + C[m, 5] * C[m, 5]) + rh[m]
        for i in range(L):
            if not near[i]:
                continue
            lim = req + SB[i, 3] + rm
            dx = SB[i, 0] - cx
            dy = SB[i, 1] - cy
            dz = SB[i, 2] - cz
            if lim > 0.0 and dx * dx + dy * dy + dz * dz >= lim * lim:
                continue  # the bounding spheres are far enough apart (a NaN never skips)
            s = _seg_dist(
                SA[i, 0], SA[i, 1], SA[i, 2], SD[i, 0], SD[i, 1], SD[i, 2],
                C[m, 0], C[m, 1], C[m, 2], C[m, 3], C[m, 4], C[m, 5],
            )  # fmt: skip
            if not (s - (ra[i] + rh[m]) >= req):
                return True
    return False


@_jit
def _pose_index(times: np.ndarray, t: float) -> int:
    """``searchsorted(times, t, side="right")`` by bisection."""
    lo = 0
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if t < times[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


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
    times: np.ndarray,
    joints: np.ndarray,
    djoints: np.ndarray,
    dtimes: np.ndarray,
    lo_pair: np.ndarray,
    hi_pair: np.ndarray,
    T_base: np.ndarray,
    t_tcp: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    off_shoulder: float,
    off_forearm: float,
    ext: np.ndarray,
    ra: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
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

    Returns ``(ok (S,) bool, exact)``: the verdicts and how many (sample, offset) pairs needed the exact
    distance.
    """
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
                _segments_one(
                    q, s, T_base, t_tcp, dh_d, dh_a, twist, off_shoulder, off_forearm, ext, X, Y, Z, P, SA, SD
                )
                have_segments = True
            _pose_at(ts, times, joints, djoints, dtimes, pose[0])
            _person_capsules(pose, 0, ia, ib, C)
            exact += 1
            if _too_close(SA, SD, near, ra, C, rh, rq, SB):
                ok[s] = False
                if n_groups > 0:
                    failed[groups[s]] = True
                break
    return ok, exact


@_jit
def _searchsorted_left(times: np.ndarray, t: float) -> int:
    """``searchsorted(times, t, side="left")`` by bisection."""
    lo = 0
    hi = times.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if times[mid] < t:
            lo = mid + 1
        else:
            hi = mid
    return lo


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
def _interp(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """``np.interp(x, xp, fp)`` for one ``x`` and increasing ``xp`` (NumPy's algorithm, without its
    per-call arrays)."""
    n = xp.shape[0]
    if n == 1:
        return fp[0]
    if x != x:
        return x
    if x < xp[0]:
        return fp[0]
    if x > xp[n - 1]:
        return fp[n - 1]
    j = _pose_index(xp, x) - 1
    if j >= n - 1 or xp[j] == x:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    r = slope * (x - xp[j]) + fp[j]
    if r != r:
        r = slope * (x - xp[j + 1]) + fp[j + 1]
        if r != r and fp[j] == fp[j + 1]:
            r = fp[j]
    return r


@_jit
def _margin_at(t: float, times: np.ndarray, margins: np.ndarray, growth: float, cap: float) -> float:
    """The forecast's margin (m) at time ``t``
    (:meth:`app.planning.search.separation._Separation._margins`)."""
    m = _interp(t, times, margins)
    if growth > 0.0:
        m = min(m + growth * max(t - times[times.shape[0] - 1], 0.0), cap)
    return m


@_jit
def _required(v: float, margin: float, prm: np.ndarray) -> float:
    """:func:`app.safety.ssm.forecast_clearance` + the extra distance (+ the SSM-aware table where
    ``prm`` carries one: :meth:`app.planning.search._Separation.ssm_extra`), capped at the floor (m);
    ``prm`` as in :func:`moves_separation_ok`."""
    req = max(v, 0.0) * prm[2] + prm[3] + prm[4] + max(prm[5], margin)
    n = prm.shape[0]
    if n > 10:  # SSM-aware: the governor's extra clearance at speed v, tabulated from prm[9] every prm[8]
        x = max(v, 0.0) / prm[8]
        i = int(x)
        if i >= n - 10:
            req += prm[n - 1]
        else:
            req += prm[9 + i] + (x - i) * (prm[10 + i] - prm[9 + i])
    return min(req + prm[6], prm[7])


@_jit
def _profile_sample(
    s: float, s_prev: float, u0: float, L: float, dur: float, f: float, A: float, end_rest: bool
) -> tuple[float, float]:
    """One sample of :func:`app.planning.search.profiles._profile_samples`: path fraction at profile time
    ``s`` and the largest path speed over ``[s_prev, s]``."""
    t1 = (f - u0) / A
    if s <= t1:
        pos = (u0 + 0.5 * A * s) * s
    else:
        pos = (u0 + 0.5 * A * t1) * t1 + f * (s - t1)
    speed = min(u0 + A * s, f)
    if end_rest:
        up = min(f, math.sqrt((2.0 * A * L + u0 * u0) / 2.0))
        if u0 * u0 <= 2.0 * A * L:
            ta = (up - u0) / A
            rem = dur - s
            if s <= ta:
                pos = (u0 + 0.5 * A * s) * s
            elif rem <= up / A:
                pos = L - 0.5 * A * rem * rem
            else:
                pos = (u0 + 0.5 * A * ta) * ta + up * (s - ta)
            speed = min(min(u0 + A * min(s, ta), up), A * (dur - s_prev))
        else:
            a_forced = u0 / max(dur, 1e-12)
            pos = u0 * s - 0.5 * a_forced * s * s
            speed = max(u0 - a_forced * s_prev, 0.0)
    frac = pos / max(L, 1e-12) if L > 1e-12 else 1.0
    return min(max(frac, 0.0), 1.0), speed


@_jit
def moves_separation_ok(
    q_a: np.ndarray,
    target: np.ndarray,
    pts_a: np.ndarray,
    cen_a: np.ndarray,
    rad_a: np.ndarray,
    pts_tab: np.ndarray,
    cen_tab: np.ndarray,
    rad_tab: np.ndarray,
    rows: np.ndarray,
    t_dep: np.ndarray,
    h: np.ndarray,
    u0: np.ndarray,
    Lp: np.ndarray,
    f: np.ndarray,
    end_rest: np.ndarray,
    hold: np.ndarray,
    lever: np.ndarray,
    moved_by: np.ndarray,
    speed_factor: float,
    A: float,
    sample_dt: float,
    hold_s: float,
    offsets: np.ndarray,
    prm: np.ndarray,
    times: np.ndarray,
    joints: np.ndarray,
    djoints: np.ndarray,
    dtimes: np.ndarray,
    lo_pair: np.ndarray,
    hi_pair: np.ndarray,
    margins: np.ndarray,
    lo_tab: np.ndarray,
    hi_tab: np.ndarray,
    T_base: np.ndarray,
    t_tcp: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    off_shoulder: float,
    off_forearm: float,
    ext: np.ndarray,
    ra: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> tuple[np.ndarray, int, int]:
    """The planner's move check (:meth:`app.planning.search.Planner._moves_ok`) in one pass.

    Move ``k`` runs straight in joint space from ``q_a[k]`` to ``target[k]`` (6,), departing at ``t_dep[k]``
    and lasting ``h[k]`` s; its path-speed profile (:func:`app.planning.search.profiles._profile_samples`) has
    entry speed ``u0``, path length ``Lp``, cruise speed ``f`` and ends at rest where ``end_rest``; where
    ``hold[k]`` the robot must then stand at the target for ``hold_s``. Robot geometry at the start: capsule
    end points ``pts_a`` (M, P, 3) and bounding spheres ``cen_a`` (M, L, 3) / ``rad_a`` (M, L); at the target:
    row ``rows[k]`` of the tables ``pts_tab``/``cen_tab``/``rad_tab``. ``lever`` (6,) bounds how far a
    joint's unit turn moves any point, ``moved_by`` (L,) is the last joint that moves each capsule (so
    ``travel`` = how far the joints can carry it), and the robot speed of a sample is its path speed times
    ``speed_factor`` x the largest chord per unit of path (as :meth:`Planner._move_prep`).

    Stage 0: a move whose capsules (the mid spheres grown by the travel) stay beyond the requirement of the
    box around the person over the move's whole time window passes. Otherwise its samples (every
    ``sample_dt`` of the move, its end, then the hold) are checked like :func:`sample_separation_ok` (each at
    every time ``offsets`` (n_off,)), and the move fails at its first sample that is too close. ``prm`` (8,):
    ``growth_mps, max_margin_m, robot_time_s, intrusion_m, z_robot_m, z_human_m, extra_m, floor_m`` (+inf:
    none); ``margins`` (H,): the forecast's margins; ``lo_tab``/``hi_tab``: the sparse table of
    :func:`_window_box`; the rest as in :func:`sample_separation_ok`.

    Returns ``(ok (M,) bool, samples, exact)``: the verdicts, the (sample, offset) pairs looked at and those
    that needed the exact distance.
    """
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
        # stage 0: the whole move (and its hold) against the person's box over its time window
        t0 = t_dep[k] + lo_off
        t1 = t_dep[k] + hk + (hold_s if hold[k] else 0.0) + hi_off
        _window_box(t0, t1, times, lo_tab, hi_tab, lo, hi)
        m_hi = max(
            hi[3],
            max(_margin_at(t0, times, margins, growth, cap), _margin_at(t1, times, margins, growth, cap)),
        )
        rq = _required(kv * peak, m_hi, prm)
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
                rq = _required(v, _margin_at(to, times, margins, growth, cap), prm)
                n_samples += 1
                ip = min(max(_pose_index(times, to) - 1, 0), n_pair - 1)
                if not _sphere_gaps_near(cen, rad, lo_pair[ip], hi_pair[ip], rq, near):
                    continue
                if not have_segments:
                    _segments_one(
                        qbuf,
                        0,
                        T_base,
                        t_tcp,
                        dh_d,
                        dh_a,
                        twist,
                        off_shoulder,
                        off_forearm,
                        ext,
                        X,
                        Y,
                        Z,
                        P,
                        SA,
                        SD,
                    )
                    have_segments = True
                _pose_at(to, times, joints, djoints, dtimes, pose[0])
                _person_capsules(pose, 0, ia, ib, C)
                n_exact += 1
                if _too_close(SA, SD, near, ra, C, rh, rq, SB):
                    ok[k] = False
                    break
            if not ok[k]:
                break
    return ok, n_samples, n_exact


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
    k_times: np.ndarray,
    k_q: np.ndarray,
    k_qd: np.ndarray,
    k_h: np.ndarray,
    eps: float,
    q_lo: np.ndarray,
    q_hi: np.ndarray,
    fc_times: np.ndarray,
    fc_joints: np.ndarray,
    fc_margins: np.ndarray,
    growth: float,
    cap: float,
    robot_time_s: float,
    intrusion_m: float,
    z_robot_m: float,
    z_human_m: float,
    floor_m: float,
    r_human_max: float,
    T_base: np.ndarray,
    t_tcp: np.ndarray,
    dh_d: np.ndarray,
    dh_a: np.ndarray,
    twist: np.ndarray,
    off_shoulder: float,
    off_forearm: float,
    ext: np.ndarray,
    ra: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> int:
    """The first sample time ``ts[k]`` (index; -1 if none) at which a trajectory leaves the joint limits or
    breaks the required separation from a forecast person (:meth:`app.planning.search.Planner._verify`).

    The trajectory: cubic Hermite knots ``k_times`` (K,), ``k_q``/``k_qd`` (K, 6), ``k_h`` (K - 1,) the knot
    intervals, evaluated at ``tq0[k]`` for the sample at wall time ``ts[k]`` (``tq0 = ts`` for a trajectory
    in wall time; a path time for a view of it that runs at another speed). Limits: ``q_lo``/``q_hi`` (6,)
    less/plus 1e-9 rad. Robot speed: the largest displacement of a capsule end between the configurations at
    ``tq0[k]`` and ``tq1[k]`` (the path time of ``ts[k] + eps``), over ``eps``. Person: the forecast
    ``fc_times`` (H,), ``fc_joints`` (H, J, 3), ``fc_margins`` (H,) interpolated as
    :meth:`HumanForecast.poses_at` does (the last pose held, the margin growing at ``growth`` m/s up to
    ``cap``); requirement :func:`app.safety.ssm.forecast_clearance` (SSM constants), capped at
    ``floor_m``. Samples are checked in order and the check stops at the first failure; a NaN counts as a
    failure.
    """
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
        _segments_one(
            q0, 0, T_base, t_tcp, dh_d, dh_a, twist, off_shoulder, off_forearm, ext, X, Y, Z, P, SA, SD
        )
        _segments_one(
            q1, 0, T_base, t_tcp, dh_d, dh_a, twist, off_shoulder, off_forearm, ext, X, Y, Z, P, SA1, SD1
        )
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
        req = v * robot_time_s + intrusion_m + z_robot_m + max(z_human_m, margin)
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
        if _too_close(SA, SD, near, ra, C, rh, req, SB):
            return k
    return -1


# ------------------------------------------------------------------------------------ search bookkeeping
# The search's state records (:class:`app.planning.search.run._Run`) as the kernels see them: one row per
# field of three packed arrays (float, int, bool) and one column per state.
REC_T, REC_U, REC_U0, REC_DEP, REC_FC, REC_L, REC_H, REC_PEAK, REC_WAIT_OK = range(9)
REC_NODE, REC_BRANCH, REC_PARENT, REC_ROW, REC_SPEC_CHILD = range(5)
REC_END, REC_SAME, REC_ACCEPTED, REC_QSET = range(4)
_EPS_T = 1e-9


@_jit
def _profile3(u0: float, L: float, f: float, A: float, end_rest: bool) -> tuple[float, float, float]:
    """Duration, exit and peak path speed of one move (:func:`app.planning.search.profiles._profile_arrays`,
    the same formulas in the same order)."""
    u0sq = u0 * u0
    two_al = 2.0 * A * L
    if not end_rest:
        u1 = min(math.sqrt(u0sq + two_al), f)
        return (u1 - u0) / A + max(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f, u1, u1
    up = min(f, math.sqrt((two_al + u0sq) / 2.0))
    if u0sq <= two_al:
        cruise = max(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
        return (up - u0) / A + cruise / max(up, 1e-12) + up / A, 0.0, up
    return 2.0 * L / max(u0, 1e-12), 0.0, u0


@_jit
def _record_move(
    n: int,
    par: int,
    node: int,
    branch: int,
    L: float,
    same: bool,
    t_dep: float,
    u0: float,
    fc: float,
    alt: int,
    row: int,
    ctx: np.ndarray,
    h_tab: np.ndarray,
    h_pred: np.ndarray,
    AT: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    alts: np.ndarray,
    keys: np.ndarray,
    tas: np.ndarray,
    n0: int,
) -> int:
    """Time one move and record it as state ``n`` if it can improve its node and passes the prune (the
    per-move body of :meth:`app.planning.search.run._Run.moves`); returns the next free state."""
    if not math.isfinite(L):
        return n
    goal = int(ctx[0])
    A = ctx[1]
    end = node == goal
    u0 = min(u0, fc)
    h, u1, peak = _profile3(u0, L, fc, A, end)
    if L > 1e-12:
        h = max(h, ctx[2])
    ta = t_dep + h
    w = ctx[3]
    stop_time = ctx[4]
    if h_tab.shape[0] > 0:
        hv = h_tab[node, branch]
    elif stop_time == stop_time:
        hv = max(stop_time - ta, 0.0)
        w = 1.0
    else:
        hv = 0.0
    if not (ta < AT[node] - _EPS_T and ta + hv <= ctx[5]):
        return n
    t_nongoal = ctx[6]
    if t_nongoal < math.inf and node != goal:
        hp = h_pred[node, branch] if h_pred.shape[0] > 0 else 0.0
        if not ta + hp < t_nongoal:
            return n
    F[REC_T, n] = ta
    F[REC_U, n] = u1
    F[REC_U0, n] = u0
    F[REC_DEP, n] = t_dep
    F[REC_FC, n] = fc
    F[REC_L, n] = L
    F[REC_H, n] = h
    F[REC_PEAK, n] = peak
    I[REC_NODE, n] = node
    I[REC_BRANCH, n] = branch
    I[REC_PARENT, n] = par
    I[REC_ROW, n] = row
    B[REC_END, n] = end
    B[REC_SAME, n] = same
    alts[n] = alt
    keys[n - n0] = ta + w * hv
    tas[n - n0] = ta
    return n + 1


@_jit
def children_moves(
    sids: np.ndarray,
    indptr: np.ndarray,
    indices: np.ndarray,
    ord_flat: np.ndarray,
    L_flat: np.ndarray,
    same_flat: np.ndarray,
    f: float,
    n_branches: int,
    ctx: np.ndarray,
    h_tab: np.ndarray,
    h_pred: np.ndarray,
    AT: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    alts: np.ndarray,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.run._Run.children` (then ``moves``): the moves from the states ``sids`` to
    all roadmap neighbours (nearest branch, cruise speed ``f``; a speculative chain's move is not made
    twice), recorded from state ``n0`` on in the same order. Returns (next free state, keys, arrival
    times) of the recorded states. ``ctx``: ``goal`` (-2: none), path acceleration, shortest move,
    heuristic weight, stop time (NaN: none), latest arrival, latest arrival at other nodes than the goal,
    cruise speed."""
    total = 0
    for s in sids:
        u = I[REC_NODE, s]
        total += indptr[u + 1] - indptr[u]
    keys = np.empty(total)
    tas = np.empty(total)
    n = n0
    for s in sids:
        u = I[REC_NODE, s]
        bu = I[REC_BRANCH, s]
        spec = I[REC_SPEC_CHILD, s]
        skip = I[REC_NODE, spec] if spec >= 0 else -1
        t = F[REC_T, s]
        us = F[REC_U, s]
        for e in range(indptr[u], indptr[u + 1]):
            v = indices[e]
            if v == skip:
                continue
            row = e * n_branches + bu
            n = _record_move(
                n, s, v, ord_flat[row, 0], L_flat[row, 0], same_flat[row, 0], t, us, f, 0, row,
                ctx, h_tab, h_pred, AT, F, I, B, alts, keys, tas, n0,
            )  # fmt: skip
    return n, keys[: n - n0], tas[: n - n0]


@_jit
def alternative_moves(
    failed: np.ndarray,
    kinds: np.ndarray,
    no_row: int,
    wait_step: float,
    t_static: float,
    start_b: np.ndarray,
    start_L: np.ndarray,
    ord_flat: np.ndarray,
    L_flat: np.ndarray,
    same_flat: np.ndarray,
    ctx: np.ndarray,
    h_tab: np.ndarray,
    h_pred: np.ndarray,
    AT: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    alts: np.ndarray,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.run._Run.alternatives` (then ``moves``): for each failed nearest-branch move
    the alternatives ``kinds`` (A, 4) = (kind, option, cruise speed, wait steps), alternative-major as
    there, recorded from state ``n0`` on. Returns as :func:`children_moves`."""
    fl = np.empty(failed.shape[0], dtype=np.int64)
    m = 0
    for s in failed:
        if alts[s] == 0 and I[REC_ROW, s] != no_row:
            fl[m] = s
            m += 1
    keys = np.empty(m * kinds.shape[0])
    tas = np.empty(m * kinds.shape[0])
    n = n0
    for a in range(kinds.shape[0]):
        kind = int(kinds[a, 0])
        opt = int(kinds[a, 1])
        fc = kinds[a, 2]
        wait = kinds[a, 3]
        for j in range(m):
            s = fl[j]
            par = I[REC_PARENT, s]
            t = F[REC_T, par]
            if not (wait <= 1 or t + (wait - 1) * wait_step < t_static):
                continue
            row = I[REC_ROW, s]
            if row >= 0:
                b = ord_flat[row, opt]
                L = L_flat[row, opt]
                same = same_flat[row, opt]
            else:
                b = start_b[-1 - row, opt]
                L = start_L[-1 - row, opt]
                same = False
            u0 = 0.0 if wait != 0 else min(F[REC_U, par], fc)
            t_dep = t + max(wait, 0.0) * wait_step
            n = _record_move(
                n, par, I[REC_NODE, s], b, L, same, t_dep, u0, fc, kind, row,
                ctx, h_tab, h_pred, AT, F, I, B, alts, keys, tas, n0,
            )  # fmt: skip
    return n, keys[: n - n0], tas[: n - n0]


@_jit
def _align1(x: float, ref: float, lo: float, hi: float) -> float:
    """One joint of :func:`align_rows`."""
    two_pi = 2.0 * math.pi
    y = x + two_pi * np.rint((ref - x) * (1.0 / two_pi))
    if y > hi:
        y = y - two_pi
    if y < lo:
        y = y + two_pi
    return x if (y > hi or y < lo) else y


@_jit
def check_prepare(
    batch: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    q: np.ndarray,
    ik: np.ndarray,
    q_lo: np.ndarray,
    q_hi: np.ndarray,
    pts_tab: np.ndarray,
    cen_tab: np.ndarray,
    rad_tab: np.ndarray,
    start_pts: np.ndarray,
    start_cen: np.ndarray,
    start_rad: np.ndarray,
    goal: int,
    hold_default: bool,
) -> tuple[np.ndarray, ...]:
    """The per-batch set-up of :meth:`app.planning.search.run._Run.check` for the states ``batch`` (M,).

    Returns ``target`` (M, 6): the state's branch aligned next to its parent's configuration (or its
    precomputed configuration), ``same`` (M,): the roadmap's static edge check covers the move (the record's
    flag, cleared where the move differs from the roadmap's), the parent's configuration ``q_par`` (M, 6)
    and capsule points/spheres ``pts_a`` (M, P, 3), ``cen_a`` (M, L, 3), ``rad_a`` (M, L) (the start's where
    the parent is not a roadmap node), the per-move floats (5, M): departure, duration, entry speed, length,
    cruise speed, and whether each move must hold at its end (M,) (at the goal; without one
    ``hold_default``), ends at rest (M,), waits before it (departs after its parent's arrival) (M,), the
    target's row ``node * 8 + branch`` (M,), the parent state (M,) and whether the move is the one between
    the stored branch configurations (M,) (the static-check memo's condition)."""
    M = batch.shape[0]
    NP = pts_tab.shape[1]
    NL = cen_tab.shape[1]
    nb = ik.shape[1]
    target = np.empty((M, 6))
    same = np.empty(M, dtype=np.bool_)
    q_par = np.empty((M, 6))
    pts_a = np.empty((M, NP, 3))
    cen_a = np.empty((M, NL, 3))
    rad_a = np.empty((M, NL))
    fl = np.empty((5, M))
    hold = np.empty(M, dtype=np.bool_)
    end = np.empty(M, dtype=np.bool_)
    waits = np.empty(M, dtype=np.bool_)
    rows = np.empty(M, dtype=np.int64)
    pars = np.empty(M, dtype=np.int64)
    stored = np.empty(M, dtype=np.bool_)
    for k in range(M):
        s = batch[k]
        par = I[REC_PARENT, s]
        pars[k] = par
        cv = I[REC_NODE, s]
        b = I[REC_BRANCH, s]
        pn = I[REC_NODE, par]
        pb = I[REC_BRANCH, par]
        for j in range(6):
            q_par[k, j] = q[par, j]
        if B[REC_QSET, s]:
            for j in range(6):
                target[k, j] = q[s, j]
        else:
            for j in range(6):
                target[k, j] = _align1(ik[cv, b, j], q_par[k, j], q_lo[j], q_hi[j])
        mv = pn >= 0  # the move is the one between the stored branch configurations
        if mv:
            for j in range(6):
                ref = ik[pn, pb, j]
                ref_t = _align1(ik[cv, b, j], ref, q_lo[j], q_hi[j])
                if not abs((ref_t - ref) - (target[k, j] - q_par[k, j])) <= 1e-9:
                    mv = False
        stored[k] = mv
        same[k] = B[REC_SAME, s] and mv
        if pn >= 0:
            r = pn * nb + pb
            for p in range(NP):
                for j in range(3):
                    pts_a[k, p, j] = pts_tab[r, p, j]
            for l in range(NL):  # noqa: E741
                for j in range(3):
                    cen_a[k, l, j] = cen_tab[r, l, j]
                rad_a[k, l] = rad_tab[r, l]
        else:
            for p in range(NP):
                for j in range(3):
                    pts_a[k, p, j] = start_pts[p, j]
            for l in range(NL):  # noqa: E741
                for j in range(3):
                    cen_a[k, l, j] = start_cen[l, j]
                rad_a[k, l] = start_rad[l]
        fl[0, k] = F[REC_DEP, s]
        fl[1, k] = F[REC_H, s]
        fl[2, k] = F[REC_U0, s]
        fl[3, k] = F[REC_L, s]
        fl[4, k] = F[REC_FC, s]
        hold[k] = cv == goal if goal != -2 else hold_default
        end[k] = B[REC_END, s]
        waits[k] = F[REC_DEP, s] > F[REC_T, par] + _EPS_T
        rows[k] = cv * nb + b
    return target, same, q_par, pts_a, cen_a, rad_a, fl, hold, end, waits, rows, pars, stored


@_jit
def check_store(
    batch: np.ndarray, ok: np.ndarray, target: np.ndarray, q: np.ndarray, status: np.ndarray
) -> None:
    """The end of :meth:`app.planning.search.run._Run.check`: the configurations of the moves that passed and
    every move's status (1 passed, 2 failed)."""
    for k in range(batch.shape[0]):
        s = batch[k]
        if ok[k]:
            for j in range(6):
                q[s, j] = target[k, j]
            status[s] = 1
        else:
            status[s] = 2


# ---------------------------------------------------------------------------------- the search's open list
# Entries (key, -t, state id) live in an append-only table (E_key, E_negt, E_id); the heap holds entry
# indices ordered as Python compares the tuples (the order is total: a state has one entry), so it pops in
# exactly the order of ``heapq`` over the tuples. ``hs`` = [heap size, entries].
POP_DONE, POP_BREAK, POP_ACCEPT, POP_ALTERNATIVES, POP_SPECULATE = range(5)


@_jit
def _less(a: int, b: int, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray) -> bool:
    if E_key[a] != E_key[b]:
        return E_key[a] < E_key[b]
    if E_negt[a] != E_negt[b]:
        return E_negt[a] < E_negt[b]
    return E_id[a] < E_id[b]


@_jit
def heap_push(
    e: int, heap: np.ndarray, hs: np.ndarray, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray
) -> None:
    """Push entry ``e`` (sift up)."""
    pos = hs[0]
    hs[0] = pos + 1
    while pos > 0:
        up = (pos - 1) >> 1
        if _less(e, heap[up], E_key, E_negt, E_id):
            heap[pos] = heap[up]
            pos = up
        else:
            break
    heap[pos] = e


@_jit
def _heap_pop(
    heap: np.ndarray, hs: np.ndarray, E_key: np.ndarray, E_negt: np.ndarray, E_id: np.ndarray
) -> int:
    top = heap[0]
    n = hs[0] - 1
    hs[0] = n
    if n == 0:
        return top
    e = heap[n]
    pos = 0
    while True:
        c = 2 * pos + 1
        if c >= n:
            break
        if c + 1 < n and _less(heap[c + 1], heap[c], E_key, E_negt, E_id):
            c += 1
        if _less(heap[c], e, E_key, E_negt, E_id):
            heap[pos] = heap[c]
            pos = c
        else:
            break
    heap[pos] = e
    return top


@_jit
def heap_add(
    ids: np.ndarray,
    keys: np.ndarray,
    ts: np.ndarray,
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
) -> None:
    """New entries (key, -t, id) for the states ``ids``, pushed in order (capacity is the caller's)."""
    for k in range(ids.shape[0]):
        e = hs[1]
        hs[1] = e + 1
        E_key[e] = keys[k]
        E_negt[e] = -ts[k]
        E_id[e] = ids[k]
        heap_push(e, heap, hs, E_key, E_negt, E_id)


@_jit
def release_deferred(
    sid: int,
    def_head: np.ndarray,
    def_next: np.ndarray,
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
) -> None:
    """Push back the entries that waited for state ``sid`` to be accepted."""
    e = def_head[sid]
    def_head[sid] = -1
    while e >= 0:
        nxt = def_next[e]
        heap_push(e, heap, hs, E_key, E_negt, E_id)
        e = nxt


@_jit
def pop_batch(
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
    def_head: np.ndarray,
    def_next: np.ndarray,
    AT: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    status: np.ndarray,
    ctx: np.ndarray,
    h_pred: np.ndarray,
    batch_len: int,
    W_b: int,
    n_popped: int,
    spec: bool,
    out: np.ndarray,
) -> tuple[int, int, int, int]:
    """The pop loop of :meth:`app.planning.search.Planner._search` up to the next step that needs Python.

    Pops entries while the heap is not empty and the batch (``batch_len`` states) is shorter than ``W_b``:
    skips states that cannot improve their node or are pruned, defers states whose parent is not accepted
    yet (dropped if it failed), pushes back a final state popped after others (and stops), and collects the
    states to check into ``out[0]`` (and the entries of the final ones among them into ``out[1]``). Returns
    ``(code, n_out, entry, n_final)``: ``POP_DONE``/``POP_BREAK`` (batch
    complete), ``POP_ACCEPT`` (``entry``'s state passed its check ahead of time: accept it),
    ``POP_ALTERNATIVES`` (it failed: push its alternatives), ``POP_SPECULATE`` (the last collected state is
    the batch's first: add its lookahead chain). ``ctx``: goal node (-2: none), stop time, pruned after the
    approach probe (0/1), latest arrival at other nodes, latest arrival, heuristic weight."""
    goal_i = int(ctx[0])
    stop = ctx[1]
    blocked = ctx[2] != 0.0
    t_nongoal = ctx[3]
    t_last = ctx[4]
    w_h = ctx[5]
    n_out = 0
    n_fin = 0
    while hs[0] > 0 and batch_len < W_b:
        e = _heap_pop(heap, hs, E_key, E_negt, E_id)
        sid = E_id[e]
        node = I[REC_NODE, sid]
        t = -E_negt[e]
        if t >= AT[node] - _EPS_T:
            continue
        if blocked and (
            (node != goal_i and t + h_pred[node, I[REC_BRANCH, sid]] >= t_nongoal)
            or t + (E_key[e] - t) / w_h > t_last + _EPS_T
        ):
            continue
        par = I[REC_PARENT, sid]
        if not B[REC_ACCEPTED, par]:
            if status[par] != 2:
                def_next[e] = def_head[par]
                def_head[par] = e
            continue
        final = node == goal_i or t >= stop
        st = status[sid]
        if final and batch_len > 0 and st != 0:
            heap_push(e, heap, hs, E_key, E_negt, E_id)
            return POP_BREAK, n_out, -1, n_fin
        if st == 1:
            return POP_ACCEPT, n_out, e, n_fin
        if st == 2:
            return POP_ALTERNATIVES, n_out, e, n_fin
        out[0, n_out] = sid
        n_out += 1
        batch_len += 1
        n_popped += 1
        if final:
            out[1, n_fin] = e
            n_fin += 1
        elif n_popped == 1 and spec:
            return POP_SPECULATE, n_out, e, n_fin
    return POP_DONE, n_out, -1, n_fin


@_jit
def speculate_chain(
    sid: int,
    max_len: int,
    nxt: np.ndarray,
    indices: np.ndarray,
    ord_flat: np.ndarray,
    L_flat: np.ndarray,
    same_flat: np.ndarray,
    delta0: np.ndarray,
    ik: np.ndarray,
    q_lo: np.ndarray,
    q_hi: np.ndarray,
    ctx: np.ndarray,
    h_tab: np.ndarray,
    h_pred: np.ndarray,
    AT: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    alts: np.ndarray,
    q: np.ndarray,
    n0: int,
) -> tuple[int, np.ndarray, np.ndarray]:
    """:meth:`app.planning.search.run._Run.speculate`: the lookahead chain of up to ``max_len`` moves from the
    unchecked state ``sid`` along ``nxt`` (per node branch, the option row of the static shortest path's
    next move, or -1), recorded from state ``n0`` on (the capacity is the caller's). ``ctx`` as in
    :func:`children_moves`. Returns (next free state, keys, arrival times)."""
    goal = int(ctx[0])
    A = ctx[1]
    min_edge = ctx[2]
    w_h = ctx[3]
    t_last = ctx[5]
    t_nongoal = ctx[6]
    f = ctx[7]
    nb = ik.shape[1]
    node = I[REC_NODE, sid]
    b = I[REC_BRANCH, sid]
    par = I[REC_PARENT, sid]
    q_prev = np.empty(6)
    if B[REC_QSET, sid]:
        for j in range(6):
            q_prev[j] = q[sid, j]
    else:
        for j in range(6):
            q_prev[j] = _align1(ik[node, b, j], q[par, j], q_lo[j], q_hi[j])
    for j in range(6):
        q[sid, j] = q_prev[j]
    B[REC_QSET, sid] = True
    t = F[REC_T, sid]
    u = F[REC_U, sid]
    keys = np.empty(max_len)
    tas = np.empty(max_len)
    n = n0
    prev = sid
    while n - n0 < max_len and node != goal:
        row = nxt[node * nb + b]
        if row < 0:
            break
        v = indices[row // nb]
        bv = ord_flat[row, 0]
        L = L_flat[row, 0]
        end = v == goal
        u0 = min(u, f)
        h, u1, peak = _profile3(u0, L, f, A, end)
        if L > 1e-12:
            h = max(h, min_edge)
        ta = t + h
        hv = h_tab[v, bv]
        if ta >= AT[v] - _EPS_T or ta + hv > t_last:
            break
        if v != goal and ta + (h_pred[v, bv] if h_pred.shape[0] > 0 else 0.0) >= t_nongoal:
            break
        inside = True
        for j in range(6):
            x = q_prev[j] + delta0[row, j]
            inside = inside and (x >= q_lo[j]) and (x <= q_hi[j])
        if inside:
            for j in range(6):
                q_prev[j] = q_prev[j] + delta0[row, j]
        else:
            for j in range(6):
                q_prev[j] = _align1(ik[v, bv, j], q_prev[j], q_lo[j], q_hi[j])
        for j in range(6):
            q[n, j] = q_prev[j]
        F[REC_DEP, n] = t
        F[REC_H, n] = h
        F[REC_T, n] = t + h
        F[REC_U, n] = u1
        F[REC_U0, n] = u0
        F[REC_FC, n] = f
        F[REC_L, n] = L
        F[REC_PEAK, n] = peak
        I[REC_ROW, n] = row
        I[REC_NODE, n] = v
        I[REC_BRANCH, n] = bv
        I[REC_PARENT, n] = prev
        I[REC_SPEC_CHILD, prev] = n
        B[REC_SAME, n] = same_flat[row, 0]
        B[REC_END, n] = end
        B[REC_QSET, n] = True
        alts[n] = 0
        keys[n - n0] = ta + w_h * hv
        tas[n - n0] = ta
        prev = n
        n += 1
        node, b, t, u = v, bv, ta, u1
    return n, keys[: n - n0], tas[: n - n0]


@_jit
def accept_checked(
    popped: np.ndarray,
    status: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    B: np.ndarray,
    AT: np.ndarray,
    goal_i: int,
    stop: float,
    def_head: np.ndarray,
    def_next: np.ndarray,
    heap: np.ndarray,
    hs: np.ndarray,
    E_key: np.ndarray,
    E_negt: np.ndarray,
    E_id: np.ndarray,
) -> tuple[int, np.ndarray, np.ndarray, int]:
    """After a batch's check (:meth:`app.planning.search.Planner._search`): the popped states, in order,
    that passed and still improve their node are accepted (``AT``, the accepted flag, their deferred
    entries pushed back); a final state is accepted only when popped first (it then ends the search).
    Returns ``(accepted, failed states, states to expand, the final state accepted or -1)``."""
    M = popped.shape[0]
    failed = np.empty(M, dtype=np.int64)
    expand = np.empty(M, dtype=np.int64)
    nf = 0
    ne = 0
    n_acc = 0
    for k in range(M):
        sid = popped[k]
        if status[sid] != 1:
            failed[nf] = sid
            nf += 1
            continue
        node = I[REC_NODE, sid]
        t = F[REC_T, sid]
        if t >= AT[node] - _EPS_T:
            continue
        if node == goal_i or t >= stop:
            if k == 0:
                AT[node] = t
                B[REC_ACCEPTED, sid] = True
                return n_acc + 1, failed[:nf], expand[:ne], sid
            continue
        AT[node] = t
        B[REC_ACCEPTED, sid] = True
        n_acc += 1
        if def_head[sid] >= 0:
            release_deferred(sid, def_head, def_next, heap, hs, E_key, E_negt, E_id)
        expand[ne] = sid
        ne += 1
    return n_acc, failed[:nf], expand[:ne], -1


@_jit
def wait_samples(
    todo: np.ndarray,
    F: np.ndarray,
    I: np.ndarray,  # noqa: E741
    q: np.ndarray,
    cen_tab: np.ndarray,
    rad_tab: np.ndarray,
    start_cen: np.ndarray,
    start_rad: np.ndarray,
    n_w: int,
    step: float,
    offsets: np.ndarray,
    times: np.ndarray,
    margins: np.ndarray,
    prm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The samples of standing still at each state of ``todo`` for :func:`sample_separation_ok` (as
    :meth:`app.planning.search.run._Run._check_waits` builds them): every ``step`` s after its arrival,
    ``n_w`` of them, at rest. Returns ``(q (S, 6), t (n_off, S), req (n_off, S), cen (S, L, 3), rad (S, L), ts
    (n, n_w))`` with ``S = n * n_w``; ``req`` is :func:`_required` at speed 0 and the margin at each time."""
    n = todo.shape[0]
    NL = cen_tab.shape[1]
    n_off = offsets.shape[0]
    nb = 8  # branches per node (app.planning.roadmap.NUM_BRANCHES)
    S = n * n_w
    qs = np.empty((S, 6))
    t_all = np.empty((n_off, S))
    req = np.empty((n_off, S))
    cen = np.empty((S, NL, 3))
    rad = np.empty((S, NL))
    ts = np.empty((n, n_w))
    growth = prm[0]
    cap = prm[1]
    for k in range(n):
        s = todo[k]
        node = I[REC_NODE, s]
        r = node * nb + I[REC_BRANCH, s]
        t0 = F[REC_T, s]
        for i in range(n_w):
            x = k * n_w + i
            ts[k, i] = t0 + step * (i + 1)
            for j in range(6):
                qs[x, j] = q[s, j]
            for l in range(NL):  # noqa: E741
                if node >= 0:
                    for j in range(3):
                        cen[x, l, j] = cen_tab[r, l, j]
                    rad[x, l] = rad_tab[r, l]
                else:
                    for j in range(3):
                        cen[x, l, j] = start_cen[l, j]
                    rad[x, l] = start_rad[l]
            for o in range(n_off):
                to = ts[k, i] + offsets[o]
                t_all[o, x] = to
                req[o, x] = _required(0.0, _margin_at(to, times, margins, growth, cap), prm)
    return qs, t_all, req, cen, rad, ts


@_jit
def wait_finish(todo: np.ndarray, ok: np.ndarray, ts: np.ndarray, wait_ok: np.ndarray) -> None:
    """``wait_ok`` of each state of ``todo``: the time of its first unsafe sample (+inf: none)."""
    n_w = ts.shape[1]
    for k in range(todo.shape[0]):
        w = math.inf
        for i in range(n_w):
            if not ok[k * n_w + i]:
                w = ts[k, i]
                break
        wait_ok[todo[k]] = w
