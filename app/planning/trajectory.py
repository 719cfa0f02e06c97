"""Plans (timed joint waypoints) and trajectories: C1 cubic joint splines within velocity/acceleration limits.

The search returns a :class:`Plan`: the robot moves in straight joint-space lines at constant speed between
the waypoints (waits are two waypoints with the same configuration). :meth:`Trajectory.from_plan` turns it
into an executable :class:`Trajectory`: a piecewise cubic Hermite spline per joint, continuous in position
and velocity, starting with the velocity ``qd0`` the robot has at the switch time and ending at rest.

Knot velocities follow a monotone rule (Fritsch-Carlson): a joint's velocity at a waypoint is 0 where
its motion changes direction (or waits) and otherwise the time-weighted average of the two neighbouring
segment speeds, limited to 3x the smaller one. So each joint stays between its waypoint values on every
segment (no overshoot past what the planner checked, except where ``qd0`` forces it), and a ramp of segment
speeds gives a ramp of velocities (constant acceleration). Where a segment would exceed the velocity or
acceleration limits it is slowed down (retimed): the later waypoints then come later than planned. The
planner therefore verifies the *fitted* trajectory against the forecast
(:meth:`app.planning.search.Planner.first_violation`) before it returns it, and stores the verified knots in
:attr:`Plan.qd` so that :meth:`Trajectory.from_plan` rebuilds exactly the verified spline.

Times are seconds on the runtime clock, joint angles radians.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from app.planning.kinematics import UR5e

_MIN_SEGMENT_S = 1e-3


class TrajectoryError(ValueError):
    """A plan cannot be turned into a trajectory (bad shapes, non-increasing times, NaN)."""


@dataclass(frozen=True, slots=True)
class Plan:
    """A timed joint-space plan.

    Attributes:
        times: Waypoint times (K,), non-decreasing, seconds on the runtime clock.
        q: Joint configurations (K, 6) in radians.
        nodes: Roadmap node index of each waypoint (K,), -1 where the waypoint is not a roadmap node
            (the start configuration, a braking knot).
        qd: Knot velocities (K, 6) in rad/s when the plan carries a fitted and verified spline (set by the
            planner); None for raw waypoints joined by constant-speed straight joint-space moves.
    """

    times: np.ndarray
    q: np.ndarray
    nodes: np.ndarray
    qd: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=np.float64)
        q = np.asarray(self.q, dtype=np.float64)
        nodes = np.asarray(self.nodes, dtype=np.int64)
        K = times.shape[0] if times.ndim == 1 else -1
        if K < 1:
            raise TrajectoryError(f"Plan.times must have shape (K,), K >= 1, got {times.shape}")
        if q.shape != (K, 6):
            raise TrajectoryError(f"Plan.q must have shape ({K}, 6), got {q.shape}")
        if nodes.shape != (K,):
            raise TrajectoryError(f"Plan.nodes must have shape ({K},), got {nodes.shape}")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(q))):
            raise TrajectoryError("Plan contains NaN or infinite times or configurations")
        if K > 1 and np.any(np.diff(times) < 0):
            raise TrajectoryError("Plan.times must be non-decreasing")
        arrays = [times, q, nodes]
        if self.qd is not None:
            qd = np.asarray(self.qd, dtype=np.float64)
            if qd.shape != (K, 6) or not np.all(np.isfinite(qd)):
                raise TrajectoryError(f"Plan.qd must be finite with shape ({K}, 6), got {qd.shape}")
            if K > 1 and np.any(np.diff(times) <= 0):
                raise TrajectoryError("a Plan with knot velocities needs strictly increasing times")
            object.__setattr__(self, "qd", qd)
            arrays.append(qd)
        for a in arrays:
            a.setflags(write=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "nodes", nodes)

    @property
    def t_start(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    @property
    def duration(self) -> float:
        return self.t_end - self.t_start

    def shifted(self, dt_s: float) -> Plan:
        """The same plan ``dt_s`` seconds later."""
        return Plan(times=self.times + dt_s, q=self.q, nodes=self.nodes, qd=self.qd)


def _default_limits() -> tuple[np.ndarray, np.ndarray]:
    from app.planning.kinematics import QD_MAX, QDD_MAX

    return np.asarray(QD_MAX, dtype=np.float64), np.asarray(QDD_MAX, dtype=np.float64)


def _monotone_velocities(times: np.ndarray, q: np.ndarray, qd0: np.ndarray) -> np.ndarray:
    """Knot velocities (K, 6): ``qd0`` first, 0 last, the monotone rule in between."""
    K = times.shape[0]
    v = np.zeros((K, 6))
    v[0] = qd0
    if K > 2:
        slopes = np.diff(q, axis=0) / np.diff(times)[:, None]
        h = np.diff(times)[:, None]
        s0, s1 = slopes[:-1], slopes[1:]
        h0, h1 = h[:-1], h[1:]
        central = (h1 * s0 + h0 * s1) / (h0 + h1)
        limit = 3.0 * np.minimum(np.abs(s0), np.abs(s1))
        same = s0 * s1 > 0.0
        v[1:-1] = np.where(same, np.sign(s0) * np.minimum(np.abs(central), limit), 0.0)
    return v


def _segment_peaks(times: np.ndarray, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Peak |velocity| and |acceleration| (K-1, 6) of each cubic Hermite segment."""
    h = np.diff(times)[:, None]
    dq = np.diff(q, axis=0)
    v0, v1 = v[:-1], v[1:]
    a0 = (6.0 * dq - 4.0 * v0 * h - 2.0 * v1 * h) / h**2
    a1 = (-6.0 * dq + 2.0 * v0 * h + 4.0 * v1 * h) / h**2
    acc = np.maximum(np.abs(a0), np.abs(a1))
    vel = np.maximum(np.abs(v0), np.abs(v1))
    denom = a0 - a1
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(np.abs(denom) > 1e-12, a0 / denom, -1.0)
    inside = (frac > 0.0) & (frac < 1.0)
    v_star = np.abs(v0 + a0 * frac * h / 2.0)
    vel = np.where(inside, np.maximum(vel, v_star), vel)
    return vel, acc


def sample_times(a: float, b: float, dt_s: float) -> np.ndarray:
    """Times (N,) every ``dt_s`` (at most) from ``a`` to ``b``, both ends included (``[a]`` when
    ``b <= a``)."""
    if dt_s <= 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    if b <= a:
        return np.array([a])
    return np.linspace(a, b, int(np.ceil((b - a) / dt_s)) + 1)


def fit_knots(
    times: np.ndarray,
    q: np.ndarray,
    *,
    qd0: np.ndarray | None = None,
    qd_max: np.ndarray,
    qdd_max: np.ndarray,
    max_iterations: int = 60,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit C1 cubic Hermite knots through timed waypoints within velocity and acceleration limits.

    Args:
        times: Waypoint times (K,), non-decreasing (a waypoint less than 1 ms after the previous one is
            dropped).
        q: Waypoints (K, 6) in radians.
        qd0: Joint velocity (6,) at ``times[0]`` (rad/s); default at rest.
        qd_max: Velocity limits (6,) in rad/s. qdd_max: acceleration limits (6,) in rad/s^2.
        max_iterations: Bound on the retiming iterations.

    Returns:
        ``(times (K', ), q (K', 6), qd (K', 6))`` with strictly increasing times; segments that were too
        fast for the limits are stretched (the following knots shift later). ``K' <= K + 1``: a plan of one
        waypoint with a non-zero ``qd0`` gets a braking knot.

    Raises:
        TrajectoryError: when the limits cannot be met within ``max_iterations`` (never for finite input).
    """
    times = np.asarray(times, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    qd_max = np.asarray(qd_max, dtype=np.float64)
    qdd_max = np.asarray(qdd_max, dtype=np.float64)
    qd0 = np.zeros(6) if qd0 is None else np.clip(np.asarray(qd0, dtype=np.float64), -qd_max, qd_max)
    if qd0.shape != (6,):
        raise TrajectoryError(f"qd0 must have shape (6,), got {qd0.shape}")
    # Merge waypoints that coincide in time (keep the earlier one: the start is where the robot is).
    keep = np.ones(times.shape[0], dtype=bool)
    keep[1:] = np.diff(times) > _MIN_SEGMENT_S
    if keep.sum() < times.shape[0]:
        idx = np.flatnonzero(keep)
        times, q = times[idx], q[idx]
    if times.shape[0] == 1:
        if not np.any(qd0 != 0.0):
            return times.copy(), q.copy(), np.zeros((1, 6))
        # Braking knot: the same configuration, reached at rest; the retiming below finds the duration.
        times = np.array([times[0], times[0] + 0.05])
        q = np.stack([q[0], q[0]])
    h = np.maximum(np.diff(times), _MIN_SEGMENT_S)
    for _ in range(max_iterations):
        t = np.concatenate([[times[0]], times[0] + np.cumsum(h)])
        v = _monotone_velocities(t, q, qd0)
        vel, acc = _segment_peaks(t, q, v)
        r_vel = np.max(vel / qd_max, axis=1)
        r_acc = np.max(acc / qdd_max, axis=1)
        bad = (r_vel > 1.0 + 1e-9) | (r_acc > 1.0 + 1e-9)
        if not np.any(bad):
            return t, q.copy(), v
        stretch = np.maximum(np.maximum(r_vel, np.sqrt(r_acc)), 1.0)
        h = np.where(bad, h * np.minimum(stretch * 1.02, 4.0), h)
    raise TrajectoryError(
        f"could not fit the plan within the joint limits after {max_iterations} retiming iterations"
    )


class Trajectory:
    """A C1 piecewise-cubic joint trajectory: ``q(t)``, ``qd(t)``, ``qdd(t)``, ``tcp(t)``.

    Before ``t_start`` it reports the first knot, after ``t_end`` it holds the final configuration at rest.
    Build it with :meth:`from_plan` (or :meth:`from_knots` for already fitted knots).
    """

    __slots__ = ("_h", "_kin", "_knots_k", "_q", "_qd", "_times", "_times_list")

    def __init__(self, times: np.ndarray, q: np.ndarray, qd: np.ndarray, *, kin: UR5e | None = None) -> None:
        times = np.asarray(times, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        qd = np.asarray(qd, dtype=np.float64)
        K = times.shape[0]
        if times.ndim != 1 or K < 1 or q.shape != (K, 6) or qd.shape != (K, 6):
            raise TrajectoryError(
                f"Trajectory knots need times (K,), q (K, 6), qd (K, 6); got {times.shape}, {q.shape}, "
                f"{qd.shape}"
            )
        if K > 1 and np.any(np.diff(times) <= 0):
            raise TrajectoryError("Trajectory knot times must be strictly increasing")
        for a in (times, q, qd):
            a.setflags(write=False)
        self._times, self._q, self._qd = times, q, qd
        self._h = np.diff(times) if K > 1 else np.ones(0)
        self._times_list = times.tolist()  # for the scalar look-up of :meth:`state`
        self._kin = kin
        self._knots_k: tuple[np.ndarray, ...] | None = None

    @classmethod
    def from_knots(
        cls, times: np.ndarray, q: np.ndarray, qd: np.ndarray, *, kin: UR5e | None = None
    ) -> Trajectory:
        """A trajectory through given knots (no fitting)."""
        return cls(times, q, qd, kin=kin)

    @classmethod
    def from_plan(
        cls,
        plan: Plan,
        *,
        qd0: np.ndarray | None = None,
        kin: UR5e | None = None,
        qd_max: np.ndarray | None = None,
        qdd_max: np.ndarray | None = None,
    ) -> Trajectory:
        """The executable trajectory of a plan.

        Args:
            plan: The plan. If it carries knot velocities (``plan.qd``, set by the planner after verifying
                the fitted spline) they are used as they are and ``qd0`` is ignored: the plan was already
                fitted with the velocity it was planned from.
            qd0: Joint velocity (6,) at ``plan.t_start`` (rad/s), the motion being executed at the switch
                time; default at rest. Only for plans without knot velocities.
            kin: Kinematics for :meth:`tcp` (optional).
            qd_max: Velocity limits (6,) in rad/s; default the UR5e limits.
            qdd_max: Acceleration limits (6,) in rad/s^2; default the UR5e limits.
        """
        if plan.qd is not None:
            return cls(plan.times, plan.q, plan.qd, kin=kin)
        if qd_max is None or qdd_max is None:
            d_qd, d_qdd = _default_limits()
            qd_max = d_qd if qd_max is None else qd_max
            qdd_max = d_qdd if qdd_max is None else qdd_max
        times, q, qd = fit_knots(plan.times, plan.q, qd0=qd0, qd_max=qd_max, qdd_max=qdd_max)
        return cls(times, q, qd, kin=kin)

    # -- knots ---------------------------------------------------------------------------------------------
    @property
    def knot_times(self) -> np.ndarray:
        """Knot times (K,)."""
        return self._times

    @property
    def knot_q(self) -> np.ndarray:
        """Knot configurations (K, 6)."""
        return self._q

    @property
    def knot_qd(self) -> np.ndarray:
        """Knot velocities (K, 6)."""
        return self._qd

    @property
    def t_start(self) -> float:
        return float(self._times[0])

    @property
    def t_end(self) -> float:
        return float(self._times[-1])

    @property
    def duration(self) -> float:
        return self.t_end - self.t_start

    def to_plan(self, nodes: np.ndarray | None = None) -> Plan:
        """The knots as a :class:`Plan` with knot velocities (rebuilds this exact trajectory)."""
        K = self._times.shape[0]
        n = np.full(K, -1, dtype=np.int64) if nodes is None else np.asarray(nodes, dtype=np.int64)
        return Plan(times=self._times, q=self._q, nodes=n, qd=self._qd)

    def shifted(self, dt_s: float) -> Trajectory:
        """The same trajectory ``dt_s`` seconds later."""
        return Trajectory(self._times + dt_s, self._q, self._qd, kin=self._kin)

    def _kernel_knots(self) -> tuple[np.ndarray, ...]:
        """Knot times (K,), configurations and velocities (K, 6) and intervals (K - 1,) as the compiled
        kernels take them (writeable contiguous copies, made once)."""
        if self._knots_k is None:
            self._knots_k = tuple(
                np.array(a, dtype=np.float64) for a in (self._times, self._q, self._qd, self._h)
            )
        return self._knots_k

    # -- evaluation ----------------------------------------------------------------------------------------
    def _locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Segment index, normalised time, before-start and after-end masks for times ``t`` (N,)."""
        times = self._times
        K = times.shape[0]
        if K == 1:
            z = np.zeros(t.shape, dtype=np.int64)
            return z, np.zeros(t.shape), np.ones(t.shape, bool), np.ones(t.shape, bool)
        idx = np.clip(np.searchsorted(times, t, side="right") - 1, 0, K - 2)
        tau = np.clip((t - times[idx]) / self._h[idx], 0.0, 1.0)
        return idx, tau, t <= times[0], t >= times[-1]

    def _eval(self, t: float | np.ndarray, order: int) -> np.ndarray:
        scalar = np.ndim(t) == 0
        tt = np.atleast_1d(np.asarray(t, dtype=np.float64))
        if tt.ndim != 1:
            raise ValueError(f"trajectory times must be a scalar or shape (N,), got {tt.shape}")
        if self._times.shape[0] == 1:
            out = np.broadcast_to(self._q[0] if order == 0 else np.zeros(6), (tt.shape[0], 6)).copy()
            return out[0] if scalar else out
        idx, tau, before, after = self._locate(tt)
        h = self._h[idx][:, None]
        p0, p1 = self._q[idx], self._q[idx + 1]
        v0, v1 = self._qd[idx], self._qd[idx + 1]
        s = tau[:, None]
        if order == 0:
            s2, s3 = s * s, s * s * s
            out = (
                (2 * s3 - 3 * s2 + 1) * p0
                + (s3 - 2 * s2 + s) * h * v0
                + (-2 * s3 + 3 * s2) * p1
                + (s3 - s2) * h * v1
            )
        elif order == 1:
            s2 = s * s
            out = (6 * s2 - 6 * s) / h * (p0 - p1) + (3 * s2 - 4 * s + 1) * v0 + (3 * s2 - 2 * s) * v1
            out = np.where(after[:, None], 0.0, out)
            out = np.where(before[:, None], self._qd[0], out)
        else:
            out = (12 * s - 6) / h**2 * (p0 - p1) + (6 * s - 4) / h * v0 + (6 * s - 2) / h * v1
            out = np.where((after | before)[:, None], 0.0, out)
        return out[0] if scalar else out

    def state(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Configuration (6,) and joint velocity (6,) at one time ``t`` (s): ``(q(t), qd(t))`` in one
        look-up (the servo loop's call)."""
        times = self._times_list
        K = len(times)
        t = float(t)
        if K == 1:
            return self._q[0].copy(), np.zeros(6)
        i = min(max(bisect.bisect_right(times, t) - 1, 0), K - 2)
        h = times[i + 1] - times[i]
        s = min(max((t - times[i]) / h, 0.0), 1.0)
        p0, p1, v0, v1 = self._q[i], self._q[i + 1], self._qd[i], self._qd[i + 1]
        s2 = s * s
        s3 = s2 * s
        q = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * h * v0
        q = q + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * h * v1
        if t >= times[-1]:
            qd = np.zeros(6)
        elif t <= times[0]:
            qd = self._qd[0].copy()
        else:
            qd = (6 * s2 - 6 * s) / h * (p0 - p1) + (3 * s2 - 4 * s + 1) * v0 + (3 * s2 - 2 * s) * v1
        return q, qd

    def q(self, t: float | np.ndarray) -> np.ndarray:
        """Configuration (6,) at a time, or (N, 6) at times (N,)."""
        return self._eval(t, 0)

    def qd(self, t: float | np.ndarray) -> np.ndarray:
        """Joint velocity (6,) or (N, 6) in rad/s (0 after ``t_end``)."""
        return self._eval(t, 1)

    def qdd(self, t: float | np.ndarray) -> np.ndarray:
        """Joint acceleration (6,) or (N, 6) in rad/s^2."""
        return self._eval(t, 2)

    def tcp(self, t: float | np.ndarray) -> np.ndarray:
        """TCP position (3,) or (N, 3) in the world frame (m).

        Raises:
            TrajectoryError: the trajectory was built without kinematics (pass ``kin=``).
        """
        if self._kin is None:
            raise TrajectoryError("Trajectory.tcp needs kinematics: build it with kin=UR5e...")
        scalar = np.ndim(t) == 0
        q = np.atleast_2d(self.q(t))
        p = self._kin.fk_tcp(q)[:, :3, 3]
        return p[0] if scalar else p

    def sample(self, dt_s: float, *, t_from: float | None = None, t_to: float | None = None) -> np.ndarray:
        """Sample times (N,) every ``dt_s`` from ``t_from`` (default ``t_start``) to ``t_to`` (default
        ``t_end``), both ends included (:func:`sample_times`)."""
        a = self.t_start if t_from is None else float(t_from)
        b = self.t_end if t_to is None else float(t_to)
        return sample_times(a, b, dt_s)

    def __repr__(self) -> str:
        return f"Trajectory(t_start={self.t_start:.3f}, t_end={self.t_end:.3f}, knots={self._times.shape[0]})"
