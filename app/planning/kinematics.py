"""UR5e kinematics: batched forward kinematics and closed-form inverse kinematics (all 8 branches).

Model: the standard UR5e Denavit-Hartenberg parameters published by Universal Robots

    ======  ========  =========  ========  =======
    joint   d (m)     a (m)      alpha     theta
    ======  ========  =========  ========  =======
    1       0.1625    0          pi/2      q1
    2       0         -0.425     0         q2
    3       0         -0.3922    0         q3
    4       0.1333    0          pi/2      q4
    5       0.0997    0          -pi/2     q5
    6       0.0996    0          0         q6
    ======  ========  =========  ========  =======

Frames: ``base`` is DH frame 0 (z along the first joint axis, origin at the bottom of the base, which is the
convention of ``ur_analytic_ik`` and of UR's own DH page; ROS' ``base_link`` is this frame turned by pi about
z). ``flange`` is DH frame 6. The robot is placed in the world by ``T_world_base`` and the tool centre point
by ``T_flange_tcp``. Lengths are metres, angles radians.

Inverse kinematics follows Hawkins, "Analytic inverse kinematics for the Universal Robots UR-5/UR-10 arms"
(2013), rewritten without 4x4 products so that a whole batch is a few dozen numpy operations. Branch ``k`` of
the 8 is ``k = 4 * shoulder + 2 * wrist + elbow`` with ``shoulder`` the sign choice of q1, ``wrist`` the sign
of sin(q5) (0: positive) and ``elbow`` the sign of q3 (0: positive).

Joint-angle representative: a joint with a +-2 pi range reaches the same pose at q and q +- 2 pi. IK returns,
for every joint, the representative within the joint limits that is closest to 0 (so in [-pi, pi] for the UR5e
limits); use :func:`align_branches` to move 2 pi-equivalent angles next to a reference configuration instead.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from app.config import R_WORLD_TOOL_DOWN, UR5E_Q_LIMIT, WorkCell
from app.planning import _kernels

__all__ = [
    "ALPHA",
    "QDD_MAX",
    "QD_MAX",
    "Q_MAX",
    "Q_MIN",
    "A",
    "D",
    "UR5e",
    "align_branches",
    "nearest_branch",
    "within_limits",
    "wrap_angle",
]

#: DH offsets along z (m), per joint.
D = np.array([0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996])
#: DH lengths along x (m), per joint.
A = np.array([0.0, -0.425, -0.3922, 0.0, 0.0, 0.0])
#: DH twists (rad), per joint.
ALPHA = np.array([math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0])
_SA = np.round(np.sin(ALPHA))  # the twists are 0 and +-pi/2: exact 0/1/-1 entries
_TWIST = _SA.copy()  # the compiled chain's twist signs (+1: pi/2, -1: -pi/2, 0: none)

_D1, _A2, _A3, _D4, _D5, _D6 = 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996

_TWO_PI = 2.0 * math.pi
#: Joint position limits (rad): elbow +-pi, the others +-2 pi (:data:`app.config.UR5E_Q_LIMIT`; a work cell
#: may narrow them, :meth:`app.config.RobotMount.joint_limits`).
Q_MAX = np.array(UR5E_Q_LIMIT, dtype=np.float64)
Q_MIN = -Q_MAX
#: Joint speed limits (rad/s).
QD_MAX = np.full(6, math.pi)
#: Joint acceleration limits (rad/s^2) used for planning: well below what the UR5e can do, so that motions
#: near a person stay smooth (UR's own default joint acceleration is 1.4 rad/s^2, its maximum several times
#: ours).
QDD_MAX = np.full(6, 4.0)

# Tolerances on the reality conditions of the closed form (squared-length and cosine units).
_REAL_TOL = 1e-10
# Below this |sin q5| the wrist is singular: q6 is free and is set to 0 (q4 absorbs the rotation).
_WRIST_SINGULAR = 1e-10


def wrap_angle(q: np.ndarray) -> np.ndarray:
    """Angles wrapped into [-pi, pi), same shape."""
    return np.mod(np.asarray(q, dtype=float) + math.pi, _TWO_PI) - math.pi


def _wrap_pi(q: np.ndarray) -> np.ndarray:
    """Wrap into [-pi, pi] (fast; exact 2 pi multiples, either end may occur at exactly +-pi)."""
    return q - _TWO_PI * np.rint(q * (1.0 / _TWO_PI))


def within_limits(q: np.ndarray, *, q_min: np.ndarray = Q_MIN, q_max: np.ndarray = Q_MAX) -> np.ndarray:
    """Whether configurations are within the joint position limits.

    Args:
        q: Joint angles (..., 6) in rad.
        q_min, q_max: Limits (6,) in rad.

    Returns:
        Boolean array (...,); False for non-finite entries.
    """
    q = np.asarray(q, dtype=float)
    if q.shape[-1:] != (6,):
        raise ValueError(f"within_limits: q must have shape (..., 6), got {q.shape}")
    return np.all((q >= q_min) & (q <= q_max), axis=-1)


def _to_limits(q: np.ndarray, q_min: np.ndarray, q_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Map every angle to its 2 pi-representative within the limits closest to 0.

    Returns ``(q_mapped, ok)`` with ``ok`` False where no representative is within the limits (or q is NaN).
    """
    w = np.mod(q + math.pi, _TWO_PI) - math.pi  # [-pi, pi): the representative closest to 0
    ok = (w >= q_min) & (w <= q_max)
    if not np.all(ok | np.isnan(w)):
        # Limits narrower than [-pi, pi] on some joint: try the neighbour representative on the other side.
        alt = w - np.copysign(_TWO_PI, w)
        alt_ok = (alt >= q_min) & (alt <= q_max)
        w = np.where(ok, w, alt)
        ok = ok | alt_ok
    return w, ok


def align_branches(
    q: np.ndarray, q_ref: np.ndarray, *, q_min: np.ndarray = Q_MIN, q_max: np.ndarray = Q_MAX
) -> np.ndarray:
    """Shift every joint by a multiple of 2 pi to be closest to a reference, staying within the limits.

    IK returns the representative closest to 0; a robot whose joint 1 stands at 3.5 rad should rather turn to
    3.5 + small than to -2.8. The result reaches exactly the same poses.

    Args:
        q: Configurations (..., 6) (for example IK branches (B, 8, 6)), rad.
        q_ref: Reference configuration(s) broadcastable to ``q`` (e.g. (6,) or (B, 1, 6)), rad.

    Returns:
        (..., 6) with each angle the 2 pi-equivalent of ``q`` nearest ``q_ref`` among those within the limits
        (the input angle itself when no shift is within the limits).
    """
    q = np.asarray(q, dtype=float)
    q_ref = np.asarray(q_ref, dtype=float)
    if q.shape[-1:] != (6,) or q_ref.shape[-1:] != (6,):
        raise ValueError(f"align_branches: shapes must end in 6, got {q.shape} and {q_ref.shape}")
    nearest = q + _TWO_PI * np.rint((q_ref - q) * (1.0 / _TWO_PI))
    ok = (nearest >= q_min) & (nearest <= q_max)
    if np.all(ok | np.isnan(nearest)):
        return nearest
    # Some nearest copies leave the limits: choose among the copies within the limits the one nearest q_ref.
    shifts = _TWO_PI * np.arange(-2.0, 3.0)
    copies = nearest[..., None] + shifts  # (..., 6, 5)
    inside = (copies >= q_min[:, None]) & (copies <= q_max[:, None])
    dist = np.where(inside, np.abs(copies - q_ref[..., None]), np.inf)
    pick = np.take_along_axis(copies, np.argmin(dist, axis=-1)[..., None], axis=-1)[..., 0]
    return np.where(np.any(inside, axis=-1), pick, q)


def nearest_branch(
    q_branches: np.ndarray,
    valid: np.ndarray,
    q_ref: np.ndarray,
    *,
    metric: Literal["l2", "max"] = "l2",
) -> tuple[np.ndarray, np.ndarray]:
    """The valid IK branch nearest a reference configuration.

    Args:
        q_branches: IK branches (..., 8, 6), rad.
        valid: Validity mask (..., 8).
        q_ref: Reference configurations (..., 6), rad.
        metric: ``"l2"`` Euclidean joint distance, or ``"max"`` the largest joint difference (with equal speed
            limits this is proportional to the time a straight joint move needs).

    Returns:
        ``(index (...,), dist (...,))``: branch index (int64) and its distance (rad); ``-1`` and ``inf`` where
        no branch is valid.
    """
    q_branches = np.asarray(q_branches, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    q_ref = np.asarray(q_ref, dtype=float)
    if q_branches.shape[-2:] != (8, 6) or valid.shape != q_branches.shape[:-1]:
        raise ValueError(
            "nearest_branch: need q_branches (..., 8, 6) and valid (..., 8), "
            f"got {q_branches.shape} and {valid.shape}"
        )
    if q_ref.shape != (*q_branches.shape[:-2], 6):
        raise ValueError(
            f"nearest_branch: q_ref must have shape {(*q_branches.shape[:-2], 6)}, got {q_ref.shape}"
        )
    diff = q_branches - q_ref[..., None, :]
    if metric == "l2":
        dist = np.sqrt(np.einsum("...i,...i->...", diff, diff))
    elif metric == "max":
        dist = np.max(np.abs(diff), axis=-1)
    else:
        raise ValueError(f"nearest_branch: metric must be 'l2' or 'max', got {metric!r}")
    dist = np.where(valid, dist, np.inf)
    index = np.argmin(dist, axis=-1)
    best = np.take_along_axis(dist, index[..., None], axis=-1)[..., 0]
    index = np.where(np.isfinite(best), index, -1)
    return index.astype(np.int64), best


def _as_transform(T: np.ndarray | None, name: str) -> np.ndarray:
    if T is None:
        return np.eye(4)
    T = np.array(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous transform, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise ValueError(f"{name} must have a proper rotation in its upper-left 3x3 block")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {T[3]}")
    return T


def _inverse_transform(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


class UR5e:
    """UR5e kinematics with a base placement and a tool.

    Args:
        T_world_base: Pose (4, 4) of DH frame 0 in the world (identity by default).
        T_flange_tcp: Pose (4, 4) of the tool centre point in the flange frame (identity by default).
        q_min, q_max: Joint position limits (6,) in rad (defaults :data:`Q_MIN`, :data:`Q_MAX`).

    The forward kinematics runs in a compiled kernel (:func:`app.planning._kernels.chain_frames`; the tests
    compare it with the NumPy chain of :class:`app.planning.reference.ReferenceUR5e`).

    All methods are batched over the first axis and fully vectorised; none keeps state between calls, so one
    instance can be shared by threads.
    """

    def __init__(
        self,
        *,
        T_world_base: np.ndarray | None = None,
        T_flange_tcp: np.ndarray | None = None,
        q_min: np.ndarray | None = None,
        q_max: np.ndarray | None = None,
    ) -> None:
        self.T_world_base = _as_transform(T_world_base, "T_world_base")
        self.T_flange_tcp = _as_transform(T_flange_tcp, "T_flange_tcp")
        self.T_base_world = _inverse_transform(self.T_world_base)
        self.T_tcp_flange = _inverse_transform(self.T_flange_tcp)
        self.q_min = Q_MIN.copy() if q_min is None else np.asarray(q_min, dtype=float).reshape(6)
        self.q_max = Q_MAX.copy() if q_max is None else np.asarray(q_max, dtype=float).reshape(6)
        if np.any(self.q_min >= self.q_max):
            raise ValueError(f"joint limits must satisfy q_min < q_max, got {self.q_min} and {self.q_max}")
        # When every joint admits all of [-pi, pi], IK angles (wrapped into [-pi, pi]) are within the limits.
        self._limits_cover_pi = bool(np.all(self.q_min <= -math.pi) and np.all(self.q_max >= math.pi))
        self._base_identity = bool(np.array_equal(self.T_world_base, np.eye(4)))
        self._tool_identity = bool(np.array_equal(self.T_flange_tcp, np.eye(4)))
        for arr in (self.T_world_base, self.T_flange_tcp, self.T_base_world, self.T_tcp_flange):
            arr.setflags(write=False)
        # writeable contiguous copies for the compiled kernels (one array type per kernel argument)
        self._T_base_k = np.array(self.T_world_base)
        self._t_tcp_k = np.array(self.T_flange_tcp[:3, 3])

    @classmethod
    def from_workcell(cls, cell: WorkCell) -> UR5e:
        """Kinematics placed as in a work cell (robot mount and tool)."""
        q_min, q_max = cell.robot.joint_limits()
        return cls(
            T_world_base=cell.robot.T_world_base(),
            T_flange_tcp=cell.tool.T_flange_tcp(),
            q_min=q_min,
            q_max=q_max,
        )

    # ------------------------------------------------------------------ forward kinematics
    def _chain(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """World-frame axes and origins of DH frames 0..6.

        Returns ``(x, y, z, p)`` each (7, 3, B) (component-major so that every step works on contiguous rows):
        the columns of the rotations and the origins.
        """
        out = _kernels.chain_frames(_kernels.as_f64(q), self._T_base_k, D, A, _TWIST)
        return out[0], out[1], out[2], out[3]

    @staticmethod
    def _check_q(q: np.ndarray, name: str) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 6:
            raise ValueError(f"{name}: q must have shape (B, 6), got {q.shape}")
        return q

    def fk(self, q: np.ndarray) -> np.ndarray:
        """Forward kinematics of every link frame.

        Args:
            q: Joint angles (B, 6), rad.

        Returns:
            (B, 7, 4, 4) world poses: index 0..5 are DH frames 1..6 (index 5 is the flange), index 6 the TCP.
        """
        q = self._check_q(q, "fk")
        x, y, z, p = self._chain(q)
        B = q.shape[0]
        out = np.zeros((B, 7, 4, 4))
        out[:, :6, :3, 0] = x[1:].transpose(2, 0, 1)
        out[:, :6, :3, 1] = y[1:].transpose(2, 0, 1)
        out[:, :6, :3, 2] = z[1:].transpose(2, 0, 1)
        out[:, :6, :3, 3] = p[1:].transpose(2, 0, 1)
        out[:, :, 3, 3] = 1.0
        if self._tool_identity:
            out[:, 6] = out[:, 5]
        else:
            out[:, 6] = out[:, 5] @ self.T_flange_tcp
        return out

    def fk_tcp(self, q: np.ndarray) -> np.ndarray:
        """World pose of the TCP, (B, 6) -> (B, 4, 4)."""
        q = self._check_q(q, "fk_tcp")
        x, y, z, p = self._chain(q)
        B = q.shape[0]
        T = np.zeros((B, 4, 4))
        T[:, :3, 0] = x[6].T
        T[:, :3, 1] = y[6].T
        T[:, :3, 2] = z[6].T
        T[:, :3, 3] = p[6].T
        T[:, 3, 3] = 1.0
        if not self._tool_identity:
            T = T @ self.T_flange_tcp
        return T

    def link_origins_and_axes(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Origins and z axes of DH frames 0..6 plus the TCP position, for collision geometry.

        Args:
            q: Joint angles (B, 6), rad.

        Returns:
            ``(p (7, 3, B), z (7, 3, B), p_tcp (3, B))`` in the world frame (m, unit vectors, m),
            component-major (the batch axis last) because the collision code consumes them that way.
        """
        q = self._check_q(q, "link_origins_and_axes")
        x, y, z, p = self._chain(q)
        t = self.T_flange_tcp[:3, 3]
        p_tcp = p[6] + t[0] * x[6] + t[1] * y[6] + t[2] * z[6]
        return p, z, p_tcp

    # ------------------------------------------------------------------ inverse kinematics
    def ik(self, T_world_tcp: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All 8 closed-form IK branches for a batch of TCP poses.

        Args:
            T_world_tcp: TCP poses (B, 4, 4) in the world frame.

        Returns:
            ``(q (B, 8, 6), valid (B, 8))``: the branches (rad, ordered ``4 * shoulder + 2 * wrist + elbow``,
            see the module docstring) and whether each is a real solution within the joint limits. Invalid
            entries hold meaningless angles. At a wrist singularity (sin q5 = 0) q6 is set to 0 and q4 takes
            the rest of the rotation.
        """
        T = np.asarray(T_world_tcp, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise ValueError(f"ik: T_world_tcp must have shape (B, 4, 4), got {T.shape}")
        if not self._base_identity:
            T = self.T_base_world @ T
        if not self._tool_identity:
            T = T @ self.T_tcp_flange
        return self._ik_base_flange(T)

    def ik_down(
        self, p_world_tcp: np.ndarray, *, yaw: float | np.ndarray = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """IK for the tool pointing straight down (TCP z = -world z), turned by ``yaw`` about world z.

        Args:
            p_world_tcp: TCP positions (B, 3), m.
            yaw: Rotation (rad) of the tool about the world z axis, scalar or (B,); 0 means
                :data:`app.config.R_WORLD_TOOL_DOWN` (TCP x = world x).

        Returns:
            Same as :meth:`ik`.
        """
        p = np.asarray(p_world_tcp, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"ik_down: p_world_tcp must have shape (B, 3), got {p.shape}")
        B = p.shape[0]
        yaw_arr = np.broadcast_to(np.asarray(yaw, dtype=float), (B,))
        cy, sy = np.cos(yaw_arr), np.sin(yaw_arr)
        T = np.zeros((B, 4, 4))
        # Rz(yaw) @ R_WORLD_TOOL_DOWN
        Rd = R_WORLD_TOOL_DOWN
        T[:, 0, :3] = cy[:, None] * Rd[0] - sy[:, None] * Rd[1]
        T[:, 1, :3] = sy[:, None] * Rd[0] + cy[:, None] * Rd[1]
        T[:, 2, :3] = Rd[2]
        T[:, :3, 3] = p
        T[:, 3, 3] = 1.0
        return self.ik(T)

    def _ik_base_flange(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closed-form IK of flange poses (B, 4, 4) given in DH frame 0."""
        B = T.shape[0]
        r11, r12, r13 = T[:, 0, 0], T[:, 0, 1], T[:, 0, 2]
        r21, r22, r23 = T[:, 1, 0], T[:, 1, 1], T[:, 1, 2]
        r31, r32, r33 = T[:, 2, 0], T[:, 2, 1], T[:, 2, 2]
        px, py, pz = T[:, 0, 3], T[:, 1, 3], T[:, 2, 3]

        # --- q1 (B, 2): the wrist-2 axis must be tangent to the circle of radius d4 about the base axis.
        a1 = px - _D6 * r13
        b1 = _D6 * r23 - py
        h = a1 * a1 + b1 * b1 - _D4 * _D4
        real1 = h >= -_REAL_TOL
        psi = np.arctan2(np.sqrt(np.maximum(h, 0.0)), _D4)
        phi = np.arctan2(a1, b1)
        q1 = np.stack([phi + psi, phi - psi], axis=1)  # (B, 2)
        c1, s1 = np.cos(q1), np.sin(q1)

        # Rows of R1 = (Rz(q1) Rx(pi/2))^T R (the wrist rotation seen from frame 1), shape (B, 2) each.
        e = (slice(None), None)
        row2x = s1 * r11[e] - c1 * r21[e]
        row2y = s1 * r12[e] - c1 * r22[e]
        c5 = s1 * r13[e] - c1 * r23[e]
        s5abs = np.sqrt(row2x * row2x + row2y * row2y)

        # --- q5 (B, 2, 2): wrist index 0 has sin q5 >= 0.
        s5 = np.stack([s5abs, -s5abs], axis=2)
        c5b = np.broadcast_to(c5[:, :, None], s5.shape)
        q5 = np.arctan2(s5, c5b)

        # --- q6 (B, 2, 2): R1[2] = (s5 c6, -s5 s6, c5); free at the wrist singularity (set to 0).
        sign5 = np.array([1.0, -1.0])
        q6 = np.arctan2(-row2y[:, :, None] * sign5, row2x[:, :, None] * sign5)
        q6 = np.where(s5abs[:, :, None] < _WRIST_SINGULAR, 0.0, q6)
        c6, s6 = np.cos(q6), np.sin(q6)

        # --- q2 + q3 + q4 (B, 2, 2): first column of R1 Rz(-q6) Ry(q5) = Rz(q234).
        vx = c5b * c6
        vy = -c5b * s6
        vz = -s5
        row0x = (c1 * r11[e] + s1 * r21[e])[:, :, None]
        row0y = (c1 * r12[e] + s1 * r22[e])[:, :, None]
        row0z = (c1 * r13[e] + s1 * r23[e])[:, :, None]
        c234 = row0x * vx + row0y * vy + row0z * vz
        s234 = r31[:, None, None] * vx + r32[:, None, None] * vy + r33[:, None, None] * vz
        q234 = np.arctan2(s234, c234)

        # --- planar 2-link problem in frame 1 for q2, q3 (B, 2, 2, 2).
        px1 = (c1 * px[e] + s1 * py[e])[:, :, None]
        py1 = (pz - _D1)[:, None, None]
        X = px1 - (_D5 * s234 - _D6 * s5 * c234)
        Y = py1 + (_D5 * c234 + _D6 * s5 * s234)
        c3 = (X * X + Y * Y - _A2 * _A2 - _A3 * _A3) / (2.0 * _A2 * _A3)
        real3 = np.abs(c3) <= 1.0 + _REAL_TOL
        c3 = np.clip(c3, -1.0, 1.0)
        s3p = np.sqrt(1.0 - c3 * c3)
        q3p = np.arctan2(s3p, c3)
        q3 = np.stack([q3p, -q3p], axis=3)  # elbow index 0: q3 >= 0
        s3 = np.stack([s3p, -s3p], axis=3)
        c3b = c3[..., None]
        q2 = np.arctan2(Y, X)[..., None] - np.arctan2(_A3 * s3, _A2 + _A3 * c3b)
        q4 = q234[..., None] - q2 - q3

        # q3, q5, q6 come from atan2 and lie in [-pi, pi] already; q1, q2, q4 are sums: wrap them.
        out = np.empty((B, 2, 2, 2, 6))
        out[..., 0] = _wrap_pi(q1)[:, :, None, None]
        out[..., 1] = _wrap_pi(q2)
        out[..., 2] = q3
        out[..., 3] = _wrap_pi(q4)
        out[..., 4] = q5[..., None]
        out[..., 5] = q6[..., None]
        q = out.reshape(B, 8, 6)
        valid = np.broadcast_to(real1[:, None, None, None] & real3[..., None], (B, 2, 2, 2)).reshape(B, 8)
        if not self._limits_cover_pi:
            q, in_lim = _to_limits(q, self.q_min, self.q_max)
            valid = valid & np.all(in_lim, axis=-1)
        return q, valid
