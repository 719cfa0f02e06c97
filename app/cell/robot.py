"""Robot backends: one protocol and a simulated UR5e; the real one over RTDE is in
:mod:`app.cell.rtde`, and :func:`app.cell.backends.make_robot` picks one by settings.

- :class:`SimRobot` is a kinematic UR5e: it tracks servo set-points within the joint position, velocity
  and acceleration limits, applies a speed scale and a latched protective stop, and steps on any
  :class:`~app.cell.clock.Clock` (lazily, up to ``clock.now()``, or explicitly with :meth:`SimRobot.step`).
- :class:`~app.cell.rtde.backend.RtdeRobot` drives a real UR over ``ur_rtde`` from a worker process (see
  :mod:`app.cell.rtde` for why a process and not a thread).

Joint positions in rad, velocities in rad/s, times in seconds on the runtime's clock.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from app.cell.clock import Clock
from app.cell.joint_tracking import JointLimits, JointTracker, ServoCommand

__all__ = [
    "RobotBackend",
    "RobotConnectionError",
    "RobotState",
    "SimRobot",
]

log = logging.getLogger(__name__)


class RobotConnectionError(RuntimeError):
    """The robot cannot be reached or the connection was lost; the message says where and what to check."""


@dataclass(frozen=True, slots=True)
class RobotState:
    """A snapshot of the arm.

    Attributes:
        t: Time of the measurement (s, runtime clock).
        q: Joint positions (6,), rad.
        qd: Joint velocities (6,), rad/s.
        protective_stop: The arm is in a protective stop (servo commands are ignored until reset).
        speed_scale: Speed scale in effect (0..1).
        connected: The backend is talking to the arm (always true for a running :class:`SimRobot`).
        fault: Why the backend is not usable, or ``None``.
    """

    t: float
    q: np.ndarray
    qd: np.ndarray
    protective_stop: bool
    speed_scale: float
    connected: bool
    fault: str | None = None

    def __post_init__(self) -> None:
        for name in ("q", "qd"):
            a = np.array(getattr(self, name), dtype=np.float64)
            if a.shape != (6,):
                raise ValueError(f"RobotState.{name} must have shape (6,), got {a.shape}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)


@runtime_checkable
class RobotBackend(Protocol):
    """What the runtime needs from an arm. All methods are thread-safe and return promptly."""

    def state(self) -> RobotState:
        """The latest state."""
        ...

    def servo(self, q: np.ndarray, qd: np.ndarray, t: float) -> None:
        """Track the set-point "at ``q`` (6,) rad with velocity ``qd`` (6,) rad/s at time ``t``"."""
        ...

    def stop(self) -> None:
        """Decelerate to rest within the acceleration limits and drop the current command."""
        ...

    def protective_stop(self) -> None:
        """Stop like :meth:`stop` and ignore servo commands until :meth:`reset_protective_stop`."""
        ...

    def reset_protective_stop(self) -> None:
        """Leave the protective stop; the arm holds still until the next servo command."""
        ...

    def set_speed_scale(self, s: float) -> None:
        """Allow at most ``s`` (0..1) of the joint speed limits."""
        ...

    def close(self) -> None:
        """Stop the arm and release every resource (idempotent)."""
        ...


def _check_scale(s: float) -> float:
    s = float(s)
    if not (0.0 <= s <= 1.0):
        raise ValueError(f"speed scale must be within [0, 1], got {s}")
    return s


class SimRobot:
    """A kinematic UR5e that tracks servo commands within its limits.

    Time: the arm integrates lazily up to ``clock.now()`` whenever it is read or commanded, so it runs on a
    :class:`~app.cell.clock.WallClock` without a thread and on a :class:`~app.cell.clock.SimClock`
    in step with the simulation. :meth:`step` integrates explicitly (the arm's own time then runs ahead of
    the clock until the clock catches up).

    Args:
        clock: The runtime's clock.
        q0: Initial joint positions (6,), rad.
        limits: Joint limits (default: the UR5e limits of :mod:`app.planning.kinematics`).
        kp: Tracking gain (1/s).
        max_substep_s: Integration step (s).
    """

    def __init__(
        self,
        clock: Clock,
        *,
        q0: np.ndarray,
        limits: JointLimits | None = None,
        kp: float = 12.0,
        max_substep_s: float = 0.004,
    ) -> None:
        self.clock = clock
        self.limits = limits if limits is not None else JointLimits.ur5e()
        self._tracker = JointTracker(q0, self.limits, kp=kp, max_substep_s=max_substep_s)
        self._t = clock.now()
        self._scale = 1.0
        self._pstop = False
        self._stopping = False
        self._closed = False
        self._ignored_servos = 0
        self._lock = threading.Lock()

    # -- time -------------------------------------------------------------------------------------------
    def _advance(self, dt_s: float) -> None:
        if dt_s <= 0:
            return
        stopping = self._pstop or self._stopping or self._closed
        self._tracker.step(self._t, dt_s, speed_scale=self._scale, stopping=stopping)
        self._t += dt_s
        if self._stopping and self._tracker.at_rest:
            self._stopping = False

    def step(self, dt_s: float) -> None:
        """Integrate ``dt_s`` >= 0 seconds beyond the arm's current time."""
        if not (dt_s >= 0 and math.isfinite(dt_s)):
            raise ValueError(f"SimRobot.step needs a finite dt_s >= 0, got {dt_s}")
        with self._lock:
            self._advance(dt_s)

    def sync(self) -> None:
        """Integrate up to ``clock.now()`` (no-op when the arm is already there)."""
        with self._lock:
            self._advance(self.clock.now() - self._t)

    # -- RobotBackend -----------------------------------------------------------------------------------
    def state(self) -> RobotState:
        with self._lock:
            self._advance(self.clock.now() - self._t)
            return RobotState(
                t=self._t,
                q=self._tracker.q.copy(),
                qd=self._tracker.qd.copy(),
                protective_stop=self._pstop,
                speed_scale=self._scale,
                connected=not self._closed,
                fault="closed" if self._closed else None,
            )

    def servo(self, q: np.ndarray, qd: np.ndarray, t: float) -> None:
        command = ServoCommand(float(t), q, qd)  # validates shapes and finiteness
        with self._lock:
            self._advance(self.clock.now() - self._t)
            if self._closed:
                raise RobotConnectionError("SimRobot is closed; create a new one to move again")
            if self._pstop:
                self._ignored_servos += 1
                if self._ignored_servos == 1:
                    log.info("servo command ignored: protective stop is active (call reset_protective_stop)")
                return
            self._stopping = False
            self._tracker.set_command(command)

    def stop(self) -> None:
        with self._lock:
            self._advance(self.clock.now() - self._t)
            self._tracker.set_command(None)
            self._stopping = True

    def protective_stop(self) -> None:
        with self._lock:
            self._advance(self.clock.now() - self._t)
            if not self._pstop:
                log.warning("protective stop at t=%.3f", self._t)
            self._pstop = True
            self._tracker.set_command(None)

    def reset_protective_stop(self) -> None:
        with self._lock:
            self._advance(self.clock.now() - self._t)
            self._pstop = False
            self._ignored_servos = 0
            self._tracker.set_command(None)
            self._stopping = not self._tracker.at_rest

    def set_speed_scale(self, s: float) -> None:
        s = _check_scale(s)
        with self._lock:
            self._advance(self.clock.now() - self._t)
            self._scale = s

    def close(self) -> None:
        with self._lock:
            self._advance(self.clock.now() - self._t)
            self._closed = True
            self._tracker.set_command(None)

    @property
    def ignored_servo_commands(self) -> int:
        """Servo commands dropped during the current protective stop."""
        return self._ignored_servos

    def __enter__(self) -> SimRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
