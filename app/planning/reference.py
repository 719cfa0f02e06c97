"""NumPy references of the planning package's compiled kinematics and capsule distances, for the tests,
benchmarks and offline scripts only (nothing at run time imports this module; ``tests/unit/test_layout.py``
checks that).

- :class:`ReferenceUR5e` is a :class:`~app.planning.kinematics.UR5e` whose forward kinematics runs in NumPy:
  the reference of :func:`app.planning._kernels.chain_frames`.
- :class:`ReferenceCollisionModel` is a :class:`~app.planning.collision.CollisionModel` on a
  :class:`ReferenceUR5e` whose capsules and robot-person and self distances are computed in NumPy: the
  reference of :func:`app.planning._kernels.robot_segments`, ``cross_min_distance``, ``paired_min_distance``,
  ``pair_distances`` and ``self_distances``. It offers the planner no compiled checks
  (:meth:`~ReferenceCollisionModel.kernel_geometry` is None), so a planner on it checks in NumPy too.
- :func:`segment_distance_reference` is :func:`app.planning.collision.segment_distance` in NumPy.

The NumPy distances run a branch-free closest-point computation (no Python loop over pairs) on blocks small
enough to stay in cache and to avoid fresh page-faulted allocations. The cross version (B x H) gets every dot
product of the segment-segment problem from one matrix product of augmented vectors (BLAS); the paired
version (K) lays the pairs out as (robot capsule, person capsule, configuration) so that every pass runs over
contiguous rows.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from app.config import WorkCell
from app.planning.collision import (
    _BLOCK_ELEMS,
    _HUMAN_A,
    _HUMAN_B,
    _NL,
    CollisionModel,
    HumanRadii,
    capsule_distance,
    joint_axis_segments,
)
from app.planning.kinematics import _SA, ALPHA, A, D, UR5e

__all__ = ["ReferenceCollisionModel", "ReferenceUR5e", "segment_distance_reference"]

_CA = np.round(np.cos(ALPHA))  # the twists are 0 and +-pi/2: exact 0/1/-1 entries
#: Batches up to this size go through the 4x4 product form of the chain.
_SMALL_BATCH = 8

_TINY = 1e-18  # m^4: below this the segments are treated as parallel (error below 1e-8 m, see _closest_sq)
_PAIRED_BLOCK = 128  # configurations per block of the paired kernel (9 x 19 x 128 pairs)


class ReferenceUR5e(UR5e):
    """A :class:`~app.planning.kinematics.UR5e` whose forward kinematics runs in NumPy (same arguments)."""

    def _chain(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`UR5e._chain` in NumPy: world-frame axes and origins of DH frames 0..6, ``(x, y, z, p)``
        each (7, 3, B)."""
        B = q.shape[0]
        if B <= _SMALL_BATCH:
            return self._chain_small(q)
        x = np.empty((7, 3, B))
        y = np.empty((7, 3, B))
        z = np.empty((7, 3, B))
        p = np.empty((7, 3, B))
        Tb = self.T_world_base
        x[0] = Tb[:3, 0, None]
        y[0] = Tb[:3, 1, None]
        z[0] = Tb[:3, 2, None]
        p[0] = Tb[:3, 3, None]
        qt = np.ascontiguousarray(q.T)
        c = np.cos(qt)
        s = np.sin(qt)
        for i in range(6):
            xp, yp, zp = x[i], y[i], z[i]
            ci, si = c[i], s[i]
            # R_i = Rz(q_i) Rx(alpha_i): first turn the parent axes about z ...
            xn = x[i + 1]
            np.multiply(ci, xp, out=xn)
            xn += si * yp
            yn = ci * yp
            yn -= si * xp
            # ... then the twist (alpha in {0, pi/2, -pi/2} permutes the axes with signs).
            if ALPHA[i] == 0.0:
                y[i + 1] = yn
                z[i + 1] = zp
            elif ALPHA[i] > 0.0:
                y[i + 1] = zp
                np.negative(yn, out=z[i + 1])
            else:
                np.negative(zp, out=y[i + 1])
                z[i + 1] = yn
            # origin: translate d along the parent z, then a along the new x.
            pn = p[i + 1]
            pn[...] = p[i]
            if D[i] != 0.0:
                pn += D[i] * zp
            if A[i] != 0.0:
                pn += A[i] * xn
        return x, y, z, p

    def _chain_small(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_chain` for a few configurations: 4x4 DH products (far fewer numpy calls per pose than
        the component-major form, which pays off from batches of a few dozen poses)."""
        B = q.shape[0]
        c, s = np.cos(q), np.sin(q)  # (B, 6)
        T = np.empty((B, 6, 4, 4))
        T[..., 0, 0] = c
        T[..., 0, 1] = -s * _CA
        T[..., 0, 2] = s * _SA
        T[..., 0, 3] = A * c
        T[..., 1, 0] = s
        T[..., 1, 1] = c * _CA
        T[..., 1, 2] = -c * _SA
        T[..., 1, 3] = A * s
        T[..., 2, 0] = 0.0
        T[..., 2, 1] = _SA
        T[..., 2, 2] = _CA
        T[..., 2, 3] = D
        T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
        frames = np.empty((7, B, 4, 4))
        frames[0] = self.T_world_base
        for i in range(6):
            np.matmul(frames[i], T[:, i], out=frames[i + 1])
        R = frames[:, :, :3, :]  # (7, B, 3, 4): columns x, y, z, p
        return tuple(np.ascontiguousarray(R[..., k].transpose(0, 2, 1)) for k in range(4))  # type: ignore[return-value]


# ----------------------------------------------------------------------------------------- distances


def _clip01(x: np.ndarray) -> None:
    np.maximum(x, 0.0, out=x)
    np.minimum(x, 1.0, out=x)


def _closest_sq(
    b: np.ndarray,
    c: np.ndarray,
    f: np.ndarray,
    rh: np.ndarray,
    a: np.ndarray,
    e: np.ndarray,
    inv_a: np.ndarray,
    inv_e: np.ndarray,
    work: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """Squared distance between segments p1 + s d1 and p2 + t d2 (s, t in [0, 1]) from their dot products.

    ``b = d1.d2, c = d1.r, f = d2.r, rh = r.r / 2, a = d1.d1, e = d2.d2`` with ``r = p1 - p2``; ``inv_a`` and
    ``inv_e`` are 1/a and 1/e (0 for a point). All broadcast to the shape of the four ``work`` arrays; the
    result is written into ``work[0]`` and returned. The squared distance is expanded in dot products, so near
    contact its square root is precise to about sqrt(round-off) * |r|, a few 1e-8 m.

    Closest points as in Ericson, Real-Time Collision Detection, 5.1.9, written without branches: the
    unconstrained s clamped, the best t for it clamped, the best s for that t clamped. This is exact (a convex
    problem; for (near-)parallel segments any clamped start gives the minimum up to |d1| * angle < 1e-8 m).
    """
    w1, w2, s, t = work
    np.multiply(a, e, out=w1)  # denominator a e - b^2
    np.multiply(b, b, out=w2)
    w1 -= w2
    np.maximum(w1, _TINY, out=w1)
    np.multiply(b, f, out=s)  # s = (b f - c e) / denominator
    np.multiply(c, e, out=w2)
    s -= w2
    s /= w1
    _clip01(s)
    np.multiply(b, s, out=t)  # t = (b s + f) / e
    t += f
    t *= inv_e
    _clip01(t)
    np.multiply(b, t, out=s)  # s = (b t - c) / a
    s -= c
    s *= inv_a
    _clip01(s)
    # |r + s d1 - t d2|^2 = 2 rh + s (a s + 2 (c - t b)) + t (e t - 2 f)
    np.multiply(t, b, out=w2)
    np.subtract(c, w2, out=w2)
    w2 *= 2.0
    np.multiply(a, s, out=w1)
    w1 += w2
    w1 *= s
    np.multiply(e, t, out=w2)
    w2 -= f
    w2 -= f
    w2 *= t
    w1 += w2
    w1 += rh
    w1 += rh
    np.maximum(w1, 0.0, out=w1)
    return w1


def _inv(x: np.ndarray) -> np.ndarray:
    return np.divide(1.0, x, out=np.zeros_like(x), where=x > _TINY)


def _work(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    return np.empty(shape), np.empty(shape), np.empty(shape), np.empty(shape)


def segment_distance_reference(p1: np.ndarray, q1: np.ndarray, p2: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """:func:`app.planning.collision.segment_distance` in NumPy: distances (...,) between segments [p1, q1]
    and [p2, q2], all (..., 3) broadcastable, m."""
    p1, q1, p2, q2 = (np.asarray(v, dtype=float) for v in (p1, q1, p2, q2))
    p1, q1, p2, q2 = np.broadcast_arrays(p1, q1, p2, q2)
    shape = p1.shape[:-1]
    # component-major (3, N): every product below is one contiguous pass
    p1, q1, p2, q2 = (np.ascontiguousarray(v.reshape(-1, 3).T) for v in (p1, q1, p2, q2))
    d1 = q1 - p1
    d2 = q2 - p2
    r = p1 - p2

    def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        out = u[0] * v[0]
        out += u[1] * v[1]
        out += u[2] * v[2]
        return out

    a, e = dot(d1, d1), dot(d2, d2)
    rh = 0.5 * dot(r, r)
    sq = _closest_sq(dot(d1, d2), dot(d1, r), dot(d2, r), rh, a, e, _inv(a), _inv(e), _work(a.shape))
    return np.sqrt(sq).reshape(shape)


# Every dot product of the segment-segment problem is one entry of a matrix product of augmented vectors:
#   robot rows  D = [d1, d1.p1, 0, 0]       P = [p1, 0, 1, |p1|^2 / 2]
#   person cols D = [d2, 0, -d2.p2, 0]      P = [-p2, 1, |p2|^2 / 2, 1]
# gives D.D = b, D.P = c = d1.(p1 - p2), P.D = f = d2.(p1 - p2), P.P = |p1 - p2|^2 / 2.
_FEATURES = 6


def _robot_features(a_c: np.ndarray, d_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Augmented robot rows (K, 2L, 6) and a = d1.d1 (K, L) from component-major segments (L, 3, K)."""
    L, _, K = a_c.shape
    U = np.zeros((K, 2 * L, _FEATURES))
    a = d_c[:, 0] * d_c[:, 0]
    dp = d_c[:, 0] * a_c[:, 0]
    pp = a_c[:, 0] * a_c[:, 0]
    for i in range(3):
        U[:, :L, i] = d_c[:, i].T
        U[:, L:, i] = a_c[:, i].T
        if i:
            a += d_c[:, i] * d_c[:, i]
            dp += d_c[:, i] * a_c[:, i]
            pp += a_c[:, i] * a_c[:, i]
    U[:, :L, 3] = dp.T
    U[:, L:, 4] = 1.0
    U[:, L:, 5] = 0.5 * pp.T
    return U, np.ascontiguousarray(a.T)


def _human_features(joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Augmented person columns (H, 6, 2M) and e = d2.d2 (H, M) for poses (H, J, 3)."""
    jt = np.ascontiguousarray(joints.transpose(1, 2, 0))  # (J, 3, H)
    p2 = jt[_HUMAN_A]  # (M, 3, H)
    d2 = jt[_HUMAN_B]
    d2 -= p2
    M, _, H = p2.shape
    V = np.zeros((H, _FEATURES, 2 * M))
    e = d2[:, 0] * d2[:, 0]
    dp = d2[:, 0] * p2[:, 0]
    pp = p2[:, 0] * p2[:, 0]
    for i in range(3):
        V[:, i, :M] = d2[:, i].T
        V[:, i, M:] = p2[:, i].T
        if i:
            e += d2[:, i] * d2[:, i]
            dp += d2[:, i] * p2[:, i]
            pp += p2[:, i] * p2[:, i]
    np.negative(V[:, :3, M:], out=V[:, :3, M:])
    V[:, 4, :M] = dp.T
    np.negative(V[:, 4, :M], out=V[:, 4, :M])
    V[:, 3, M:] = 1.0
    V[:, 4, M:] = 0.5 * pp.T
    V[:, 5, M:] = 1.0
    return V, np.ascontiguousarray(e.T)


def _cross_min_distance(
    U: np.ndarray, a: np.ndarray, ra: np.ndarray, V: np.ndarray, e: np.ndarray, rh: np.ndarray
) -> np.ndarray:
    """Min signed distance between every robot configuration and every person pose.

    Args:
        U, a: Robot features (B, 2L, 6) and squared segment lengths (B, L) (:func:`_robot_features`).
        ra: Robot radii (L,).
        V, e: Person features (H, 6, 2M) and squared segment lengths (H, M) (:func:`_human_features`).
        rh: Person radii (M,).

    Returns:
        (B, H) minimum over the L x M capsule pairs.
    """
    B, L = a.shape
    H, M = e.shape
    out = np.empty((B, H))
    hb = max(1, min(H, _BLOCK_ELEMS // (L * M)))  # poses per block
    rows = max(1, min(B, _BLOCK_ELEMS // (L * M * hb)))  # configurations per block
    rsum = (ra[:, None] + rh[None, :])[:, None, :]  # (L, 1, M)
    inv_a = _inv(a)
    inv_e = _inv(e)
    work = _work((rows * L, hb * M))
    for h0 in range(0, H, hb):
        h1 = min(H, h0 + hb)
        nh = (h1 - h0) * M
        # columns [D of every pose, then P of every pose]
        Vb = V[h0:h1].reshape(h1 - h0, _FEATURES, 2, M).transpose(1, 2, 0, 3).reshape(_FEATURES, 2 * nh)
        eb = e[h0:h1].reshape(1, nh)
        ieb = inv_e[h0:h1].reshape(1, nh)
        for b0 in range(0, B, rows):
            b1 = min(B, b0 + rows)
            n = (b1 - b0) * L
            Ub = U[b0:b1].reshape(b1 - b0, 2, L, _FEATURES).transpose(1, 0, 2, 3).reshape(2 * n, _FEATURES)
            G = Ub @ Vb  # (2n, 2nh): [b, c; f, rr / 2]
            w = work if n == work[0].shape[0] and nh == work[0].shape[1] else _work((n, nh))
            sq = _closest_sq(
                G[:n, :nh],
                G[:n, nh:],
                G[n:, :nh],
                G[n:, nh:],
                a[b0:b1].reshape(n, 1),
                eb,
                inv_a[b0:b1].reshape(n, 1),
                ieb,
                w,
            )
            dist = np.sqrt(sq, out=sq).reshape(b1 - b0, L, h1 - h0, M)
            dist -= rsum
            out[b0:b1, h0:h1] = dist.min(axis=(1, 3))
    return out


def _paired_min_distance(
    a_c: np.ndarray,
    d_c: np.ndarray,
    ra: np.ndarray,
    jt: np.ndarray,
    ia: np.ndarray,
    ib: np.ndarray,
    rh: np.ndarray,
) -> np.ndarray:
    """Min signed distance between robot configuration k and person pose k.

    Works in an (L, M, k) layout, configurations innermost: every robot quantity (L, 1, k) and person quantity
    (1, M, k) broadcasts along an outer axis, so each numpy pass runs over contiguous rows.

    Args:
        a_c, d_c: Robot segment starts and directions, component-major (L, 3, K).
        ra: Robot radii (L,).
        jt: Person poses, component-major (J, 3, K).
        ia, ib: Joint indices (M,) of the person capsules' ends.
        rh: Person radii (M,).

    Returns:
        (K,) minimum over the L x M capsule pairs of each k.
    """
    L, _, K = a_c.shape
    M = len(rh)
    kb = max(1, min(K, _PAIRED_BLOCK))
    a = np.einsum("lik,lik->lk", d_c, d_c)
    inv_a = _inv(a)
    rsum = (ra[:, None] + rh[None, :])[:, :, None]
    out = np.empty(K)
    shape = (L, M, kb)
    b, c, f, rr, tmp = (np.empty(shape) for _ in range(5))
    work = _work(shape)
    for k0 in range(0, K, kb):
        k1 = min(K, k0 + kb)
        m = k1 - k0
        if m != kb:
            b, c, f, rr, tmp = (x[:, :, :m] for x in (b, c, f, rr, tmp))
            work = tuple(w[:, :, :m] for w in work)  # type: ignore[assignment]
        d1 = d_c[:, :, None, k0:k1]  # (L, 3, 1, m)
        p1 = a_c[:, :, None, k0:k1]
        p2 = jt[ia, :, k0:k1]  # (M, 3, m)
        d2 = jt[ib, :, k0:k1]
        d2 -= p2
        e = np.einsum("mik,mik->mk", d2, d2)[None]  # (1, M, m)
        d2 = d2.transpose(1, 0, 2)[:, None]  # (3, 1, M, m)
        p2 = p2.transpose(1, 0, 2)[:, None]
        r = work[0]
        np.multiply(d1[:, 0], d2[0], out=b)
        for i in range(3):
            np.subtract(p1[:, i], p2[i], out=r)  # r = p1 - p2, one component
            if i:
                np.multiply(d1[:, i], d2[i], out=tmp)
                b += tmp
                np.multiply(d1[:, i], r, out=tmp)
                c += tmp
                np.multiply(d2[i], r, out=tmp)
                f += tmp
                np.multiply(r, r, out=tmp)
                rr += tmp
            else:
                np.multiply(d1[:, 0], r, out=c)
                np.multiply(d2[0], r, out=f)
                np.multiply(r, r, out=rr)
        rr *= 0.5
        sq = _closest_sq(b, c, f, rr, a[:, None, k0:k1], e, inv_a[:, None, k0:k1], _inv(e), work)
        dist = np.sqrt(sq, out=sq)
        dist -= rsum
        out[k0:k1] = dist.min(axis=(0, 1))
    return out


class ReferenceCollisionModel(CollisionModel):
    """A :class:`~app.planning.collision.CollisionModel` that computes in NumPy (the same arguments; the
    kinematics default to :class:`ReferenceUR5e`)."""

    def __init__(
        self,
        cell: WorkCell,
        *,
        kin: UR5e | None = None,
        human_radii: HumanRadii | Mapping[str, float] | np.ndarray | None = None,
    ) -> None:
        super().__init__(
            cell, kin=kin if kin is not None else ReferenceUR5e.from_workcell(cell), human_radii=human_radii
        )

    def _robot_segments_cm(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p, z, p_tcp = self.kin.link_origins_and_axes(q)  # (7, 3, B), (7, 3, B), (3, B)
        a, d = joint_axis_segments(p, z, p_tcp, self.tool_end_fraction)
        f = self._k_ext  # (L, 2): the extensions as fractions of each segment's length
        a -= f[:, 0, None, None] * d
        d *= (1.0 + f[:, 0] + f[:, 1])[:, None, None]
        return a, d

    def distance_to_human(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        q = self._check_q(q, "distance_to_human")
        joints = self._check_joints(joints, "distance_to_human")
        if q.shape[0] == 0 or joints.shape[0] == 0:
            return np.empty((q.shape[0], joints.shape[0]))
        U, a = _robot_features(*self._robot_segments_cm(q))
        V, e = _human_features(joints)
        return _cross_min_distance(U, a, self.robot_radii, V, e, self.human_radii)

    def distance_to_human_paired(
        self,
        q: np.ndarray,
        joints: np.ndarray,
        *,
        segments: tuple[np.ndarray, np.ndarray] | None = None,
        links: np.ndarray | None = None,
        capsules: np.ndarray | None = None,
    ) -> np.ndarray:
        q = self._check_q(q, "distance_to_human_paired")
        joints = self._check_joints(joints, "distance_to_human_paired")
        if joints.shape[0] != q.shape[0]:
            raise ValueError(
                f"distance_to_human_paired: q (K, 6) and joints (K, J, 3) need the same K, "
                f"got {q.shape[0]} and {joints.shape[0]}"
            )
        if q.shape[0] == 0:
            return np.empty(0)
        a_c, d_c = self._robot_segments_cm(q) if segments is None else segments
        if a_c.shape != (_NL, 3, q.shape[0]) or d_c.shape != a_c.shape:
            raise ValueError(
                f"distance_to_human_paired: segments must be ({_NL}, 3, K) each, got {a_c.shape}"
            )
        ra, ia, ib, rh = self.robot_radii, _HUMAN_A, _HUMAN_B, self.human_radii
        if links is not None:
            if len(links) == 0:
                return np.full(q.shape[0], np.inf)
            a_c, d_c, ra = a_c[links], d_c[links], ra[links]
        if capsules is not None:
            if len(capsules) == 0:
                return np.full(q.shape[0], np.inf)
            ia, ib, rh = ia[capsules], ib[capsules], rh[capsules]
        jt = np.ascontiguousarray(joints.transpose(1, 2, 0))  # (J, 3, K)
        return _paired_min_distance(a_c, d_c, ra, jt, ia, ib, rh)

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (6,):
            raise ValueError(f"pair_distances: q must have shape (6,), got {q.shape}")
        joints = self._check_joints(joints, "pair_distances")
        ra, rb, rr = self.robot_capsules(q[None])
        ha, hb, hr = self.human_capsules(joints)
        return capsule_distance(
            ra[0][None, :, None, :],
            rb[0][None, :, None, :],
            rr[None, :, None],
            ha[:, None, :, :],
            hb[:, None, :, :],
            hr[None, None, :],
        )

    def kernel_geometry(self) -> None:
        """None: this model offers the planner no compiled checks."""
        return None

    def self_distances(
        self, q: np.ndarray, *, segments: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        q = self._check_q(q, "self_distances")
        pa, pd = self._segments_bl(q, segments)
        i, j = self._self_i, self._self_j
        return capsule_distance(
            pa[:, i],
            pa[:, i] + pd[:, i],
            self.self_radii[i],
            pa[:, j],
            pa[:, j] + pd[:, j],
            self.self_radii[j],
        )
