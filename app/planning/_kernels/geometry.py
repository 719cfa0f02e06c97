"""Kernels of the robot's and the person's geometry: UR5e forward kinematics to capsule segments, the
row-wise 2 pi alignment of configurations, and segment-segment and robot-person capsule distances.

The forward kinematics performs the same operations in the same order as the component-major NumPy chain
(:meth:`app.planning.kinematics.UR5e._chain`). Layouts: robot segments are *component-major* ``(L, 3, B)``
(starts ``a`` and directions ``d = end - start``), as
:meth:`app.planning.collision.CollisionModel.robot_segments` returns them; person poses are ``(H, J, 3)``
and a person capsule ``m`` runs from joint ``ia[m]`` to joint ``ib[m]``.
"""

from __future__ import annotations

import math

import numpy as np

from app.planning._kernels.arrays import RobotArrays
from app.planning._kernels.base import _NL, _jit, _nan_min, _seg_dist

__all__ = [
    "align_rows",
    "chain_frames",
    "cross_min_distance",
    "pair_distances",
    "paired_min_distance",
    "robot_segments",
    "segment_distances",
    "self_distances",
]


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
    robot: RobotArrays,
    X: np.ndarray,
    Y: np.ndarray,
    Z: np.ndarray,
    P: np.ndarray,
    SA: np.ndarray,
    SD: np.ndarray,
) -> None:
    """Robot capsule segments (9, 3) starts ``SA`` and directions ``SD`` for configuration ``q[k]``, as
    :meth:`app.planning.collision.CollisionModel._robot_segments_cm` lays them out. ``X``, ``Y``, ``Z``,
    ``P`` (7, 3): scratch (the DH frames' axes and origins)."""
    t_tcp = robot.t_tcp
    off_shoulder = robot.off_shoulder
    off_forearm = robot.off_forearm
    ext = robot.ext
    _chain_one(q, k, robot.T_base, robot.dh_d, robot.dh_a, robot.twist, X, Y, Z, P)
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
    for l in range(_NL):  # noqa: E741  (the extensions, as app.planning.reference.ReferenceCollisionModel._robot_segments_cm)
        f0 = ext[l, 0]
        s = 1.0 + f0 + ext[l, 1]
        for j in range(3):
            SA[l, j] -= f0 * SD[l, j]
            SD[l, j] *= s


@_jit
def robot_segments(q: np.ndarray, robot: RobotArrays) -> tuple[np.ndarray, np.ndarray]:
    """Robot capsule segments for configurations ``q`` (B, 6): starts and directions (9, 3, B) each (m).

    ``robot``: the capsule model (its radii are not needed here): ``t_tcp`` (3,) the tool capsule's end in
    the flange frame (m); ``off_shoulder``/``off_forearm``: the offsets of the upper-arm and forearm centre
    lines along the shoulder axis (m); ``ext`` (9, 2): how far each segment reaches beyond its joint-axis
    start and end, as fractions of its length."""
    robot = RobotArrays(*robot)
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
        _segments_one(q, k, robot, X, Y, Z, P, SA, SD)
        for l in range(_NL):  # noqa: E741
            for j in range(3):
                a[l, j, k] = SA[l, j]
                d[l, j, k] = SD[l, j]
    return a, d


# ------------------------------------------------------------------------------------------ alignment


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
