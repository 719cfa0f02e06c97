"""Joint-space servo tracking within position, velocity and acceleration limits (no I/O).

Shared by :class:`~app.cell.robot.SimRobot` (the tracker *is* the simulated arm) and the RTDE worker
(the tracker shapes the set-points sent with ``servoJ``), so the real and the simulated arm obey the same
limits, speed scale and stopping behaviour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from app.cell._kernels import JointTrackerParams, TrackerCommand, track_substeps

__all__ = ["JointLimits", "JointTracker", "ServoCommand", "warm_up_compiled"]


def _vec6(x: object, name: str) -> np.ndarray:
    a = np.array(x, dtype=np.float64).reshape(-1)
    if a.shape != (6,):
        raise ValueError(f"{name} must have shape (6,), got {np.shape(x)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    return a


@dataclass(frozen=True)
class JointLimits:
    """Per-joint limits of a 6-axis arm.

    Attributes:
        q_min: Lower position limits (6,), rad.
        q_max: Upper position limits (6,), rad.
        qd_max: Speed limits (6,), rad/s, > 0.
        qdd_max: Acceleration limits (6,), rad/s^2, > 0.
        brake_decel: How fast each joint can slow down (6,), rad/s^2, >= ``qdd_max``: a braking joint may
            lose speed this fast, a joint speeding up gains it at ``qdd_max`` at most. None: ``qdd_max``.
    """

    q_min: np.ndarray
    q_max: np.ndarray
    qd_max: np.ndarray
    qdd_max: np.ndarray
    brake_decel: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.brake_decel is None:
            object.__setattr__(self, "brake_decel", self.qdd_max)
        for name in ("q_min", "q_max", "qd_max", "qdd_max", "brake_decel"):
            a = _vec6(getattr(self, name), name)
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        if np.any(self.q_min >= self.q_max):
            raise ValueError(f"q_min must be < q_max, got {self.q_min} and {self.q_max}")
        if np.any(self.qd_max <= 0) or np.any(self.qdd_max <= 0):
            raise ValueError("qd_max and qdd_max must be > 0")
        if np.any(self.brake_decel < self.qdd_max):
            raise ValueError(f"brake_decel must be >= qdd_max, got {self.brake_decel} and {self.qdd_max}")

    @classmethod
    def ur5e(cls) -> JointLimits:
        """The UR5e limits from :mod:`app.planning.kinematics` (Q_MIN, Q_MAX, QD_MAX, QDD_MAX), braking as
        the manual's stops do (:data:`app.safety.stopping.UR5_MANUAL_JOINT_DECEL_RADPS2`; the stopping
        model counts on 60 % of that)."""
        from app.planning.kinematics import Q_MAX, Q_MIN, QD_MAX, QDD_MAX
        from app.safety.stopping import UR5_MANUAL_JOINT_DECEL_RADPS2

        qdd = np.asarray(QDD_MAX, dtype=float)
        return cls(
            q_min=np.asarray(Q_MIN, dtype=float),
            q_max=np.asarray(Q_MAX, dtype=float),
            qd_max=np.asarray(QD_MAX, dtype=float),
            qdd_max=qdd,
            brake_decel=np.maximum(np.asarray(UR5_MANUAL_JOINT_DECEL_RADPS2, dtype=float), qdd),
        )

    def as_lists(self) -> dict[str, list[float]]:
        """Plain lists (picklable without numpy, e.g. for the RTDE worker process)."""
        names = ("q_min", "q_max", "qd_max", "qdd_max", "brake_decel")
        return {k: getattr(self, k).tolist() for k in names}


@dataclass(frozen=True)
class ServoCommand:
    """A servo set-point: be at ``q`` with velocity ``qd`` at time ``t``.

    Attributes:
        t: Time of the set-point (s, runtime clock).
        q: Joint positions (6,), rad.
        qd: Joint velocities (6,), rad/s (feed-forward; zero for a hold).
    """

    t: float
    q: np.ndarray
    qd: np.ndarray

    def __post_init__(self) -> None:
        if not math.isfinite(self.t):
            raise ValueError(f"servo time must be finite, got {self.t}")
        q = _vec6(self.q, "servo q")
        qd = _vec6(self.qd, "servo qd")
        q.setflags(write=False)
        qd.setflags(write=False)
        object.__setattr__(self, "q", q)
        object.__setattr__(self, "qd", qd)


class JointTracker:
    """A kinematic joint-space tracker: follows servo set-points within the limits.

    The reference at time ``tau`` is the command extrapolated with its velocity,
    ``q_ref = q + qd * (tau - t)``, for at most ``hold_after_s``; after that it holds (zero feed-forward),
    so a command stream that stops brings the arm to rest. The desired velocity is the feed-forward plus a
    feedback that can always stop in time, ``sign(e) * min(kp |e|, sqrt(2 a |e|))``; the whole velocity
    vector is scaled down uniformly to respect ``speed_scale * qd_max`` (the path direction is kept), then
    each joint's change of velocity is limited by ``qdd_max`` (by ``brake_decel`` where it slows down).
    Positions are clipped to the limits.

    Args:
        q0: Initial joint positions (6,), rad.
        limits: Joint limits.
        kp: Feedback gain (1/s).
        hold_after_s: How long (s) a command is extrapolated with its velocity.
        max_substep_s: Integration step (s); :meth:`step` subdivides longer steps.
    """

    def __init__(
        self,
        q0: np.ndarray,
        limits: JointLimits,
        *,
        kp: float = 12.0,
        hold_after_s: float = 0.1,
        max_substep_s: float = 0.002,
    ) -> None:
        self.limits = limits
        self.kp = float(kp)
        self.hold_after_s = float(hold_after_s)
        self.max_substep_s = float(max_substep_s)
        q = np.clip(_vec6(q0, "q0"), limits.q_min, limits.q_max)
        self.q = q
        self._qdd_max = np.array(limits.qdd_max)
        self._inv_qd_max = 1.0 / limits.qd_max
        # Targets stay a hair inside the limits, so the braking never touches the hard clip of the positions.
        self._ref_lo = limits.q_min + 1e-4
        self._ref_hi = limits.q_max - 1e-4
        self.qd = np.zeros(6)
        self.command: ServoCommand | None = None
        # the compiled loop's arguments (kp and hold_after_s are fixed from here on)
        self._params = JointTrackerParams(
            self.hold_after_s,
            self.kp,
            self._ref_lo,
            self._ref_hi,
            limits.q_min,
            limits.q_max,
            self._qdd_max,
            self._inv_qd_max,
            np.array(limits.brake_decel),
        )
        no_command = np.zeros(6)
        self._hold = TrackerCommand(0.0, no_command, no_command, False)
        self._command = self._hold

    def set_command(self, command: ServoCommand | None) -> None:
        """Track ``command`` from now on (``None``: hold the current position)."""
        if command is not None:
            q_target = np.minimum(np.maximum(command.q, self._ref_lo), self._ref_hi)
            if not np.array_equal(q_target, command.q):
                command = ServoCommand(command.t, q_target, command.qd)
        self.command = command
        self._command = (
            self._hold if command is None else TrackerCommand(float(command.t), command.q, command.qd, True)
        )

    def reference(self, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference position (6,) rad and feed-forward velocity (6,) rad/s at time ``tau``."""
        c = self.command
        if c is None:
            return self.q.copy(), np.zeros(6)
        lead = tau - c.t
        if lead > self.hold_after_s:
            q_ref, qd_ref = c.q + c.qd * self.hold_after_s, np.zeros(6)
        else:
            q_ref, qd_ref = c.q + c.qd * lead, c.qd
        return np.minimum(np.maximum(q_ref, self._ref_lo), self._ref_hi), qd_ref

    def step(self, t: float, dt_s: float, *, speed_scale: float = 1.0, stopping: bool = False) -> None:
        """Integrate from time ``t`` over ``dt_s`` seconds.

        Args:
            t: Time (s) at the start of the step (for the command's extrapolation).
            dt_s: Step length (s), >= 0.
            speed_scale: Fraction (0..1) of ``qd_max`` allowed.
            stopping: Decelerate to rest within ``brake_decel`` (all joints stop together, so the arm stays
                on its joint-space path), ignoring the command.
        """
        n, h, s = self._substeps(dt_s, speed_scale)
        if n == 0:
            return
        track_substeps(self.q, self.qd, float(t), h, n, s, bool(stopping), self._command, self._params)

    def _substeps(self, dt_s: float, speed_scale: float) -> tuple[int, float, float]:
        """Number and length (s) of the substeps of a step of ``dt_s`` >= 0 seconds, and the speed scale
        clipped to [0, 1]."""
        if dt_s < 0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        n = max(1, math.ceil(dt_s / self.max_substep_s - 1e-9)) if dt_s > 0 else 0
        return n, (dt_s / n if n else 0.0), min(max(float(speed_scale), 0.0), 1.0)

    @property
    def at_rest(self) -> bool:
        """True when every joint speed is zero."""
        return not np.any(self.qd)


def warm_up_compiled(limits: JointLimits | None = None) -> None:
    """Load (on a fresh install: compile) the tracker's compiled loop by stepping a throwaway tracker, so
    that the first step of a real control loop does not stall it (call before the loop starts)."""
    limits = limits if limits is not None else JointLimits.ur5e()
    q0 = 0.5 * (limits.q_min + limits.q_max)
    tracker = JointTracker(q0, limits)
    tracker.set_command(ServoCommand(0.0, q0 + 0.01, np.full(6, 0.1)))
    tracker.step(0.0, 0.004)
    tracker.step(0.004, 0.004, stopping=True)
