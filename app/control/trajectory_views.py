"""What the supervisor needs from the planner, the trajectories and the robot model (structural types), and
the trajectory views it executes: a held pose, a time-scaled view of a trajectory, its speed profile."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from app.prediction.forecast import HumanForecast
from app.safety.stopping import UR5E_STOP

#: A goal of a planning query: a task pose's name or a roadmap node.
Goal = str | int


# ----------------------------------------------------------------------------------------------------
# What the supervisor needs from the planner, the trajectories and the robot model (structural types).
# ----------------------------------------------------------------------------------------------------


class TrajectoryLike(Protocol):
    """A time-parametrised joint trajectory (holds its final configuration after ``t_end``)."""

    @property
    def t_start(self) -> float: ...

    @property
    def t_end(self) -> float: ...

    def q(self, t: Any) -> np.ndarray: ...

    def qd(self, t: Any) -> np.ndarray: ...


class PlanResultLike(Protocol):
    ok: bool
    plan: Any
    reason: str
    expanded: int
    compute_s: float


class PlannerLike(Protocol):
    """The subset of :class:`app.planning.search.Planner` the supervisor uses."""

    def plan(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        goal: Goal,
        forecast: HumanForecast | None,
        workers: int = 1,
        deadline_s: float | None = None,
        qd0: np.ndarray | None = None,
        timing: Any = None,
    ) -> PlanResultLike: ...

    def emergency(
        self, *, q_start: np.ndarray, t_start: float, forecast: HumanForecast, horizon_s: float
    ) -> PlanResultLike: ...

    def first_violation(
        self, traj: Any, forecast: HumanForecast, *, t_from: float, t_to: float, dt_s: float | None = None
    ) -> float | None: ...

    def predicted_check(
        self, traj: Any, forecast: HumanForecast | None, *, timing: Any = None
    ) -> tuple[float | None, float]: ...

    def with_timer(self, timer: Callable[[], float]) -> PlannerLike:
        """This planner reading deadlines and compute times from ``timer``."""
        ...


class RobotGeometry(Protocol):
    """The robot's body as ``L`` parts (see :class:`app.control.stack.CellGeometry`: one per capsule)."""

    def part_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Surface distance (P, L) in m between each part of the robot at ``q`` (6,) and the person in each
        of the poses ``joints`` (P, J, 3)."""
        ...

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Speed (K, L) in m/s of each part (its fastest point) for ``q``, ``qd`` (K, 6)."""
        ...

    def path_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Surface distance (K, L) in m between each part of the robot at each of ``q`` (K, 6) and the
        person at ``joints`` (J, 3) (the same distance as :meth:`part_separations`)."""
        ...

    def near_person(
        self, q: np.ndarray, joints: np.ndarray, joints_before: np.ndarray, dt_s: float, *, band_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """For the robot at ``q`` (6,) and the person at ``joints`` (J, 3), who was at ``joints_before``
        ``dt_s`` earlier: each part's separation (L,) (m) and the person's directed speed toward it (L,)
        (m/s): the fastest approach of the person's parts within ``band_m`` of being the nearest to it."""
        ...


MakeTrajectory = Callable[[Any, np.ndarray | None], TrajectoryLike]
"""``make_trajectory(plan, qd0)``: a trajectory through ``plan`` starting with joint velocity ``qd0``."""


# ----------------------------------------------------------------------------------------------------
# Trajectory helpers
# ----------------------------------------------------------------------------------------------------


class HoldTrajectory:
    """The robot held at ``q`` (6,): the "plan" of a robot that is not going anywhere."""

    def __init__(self, q: np.ndarray, t0: float) -> None:
        q = np.asarray(q, dtype=np.float64).reshape(6).copy()
        q.setflags(write=False)
        self._q = q
        self._t0 = float(t0)

    @property
    def t_start(self) -> float:
        return self._t0

    @property
    def t_end(self) -> float:
        return self._t0

    @property
    def duration(self) -> float:
        return 0.0

    def q(self, t: Any) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.broadcast_to(self._q, (*t.shape, 6)).copy()

    def qd(self, t: Any) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.zeros((*t.shape, 6))

    def sample(self, dt_s: float, *, t_from: float | None = None, t_to: float | None = None) -> np.ndarray:
        return _sample(self.t_start, self.t_end, dt_s, t_from, t_to)


def _sample(
    t_start: float, t_end: float, dt_s: float, t_from: float | None, t_to: float | None
) -> np.ndarray:
    if dt_s <= 0:
        raise ValueError(f"dt_s must be > 0, got {dt_s}")
    a = t_start if t_from is None else float(t_from)
    b = t_end if t_to is None else float(t_to)
    if b <= a:
        return np.array([a])
    return np.linspace(a, b, math.ceil((b - a) / dt_s) + 1)


class ScaledView:
    """A trajectory seen in wall time: at wall time ``t >= t_ref`` the robot is at path time
    ``tau_ref + scale * (t - t_ref)`` of ``traj``. Used to check the plan in execution (and a backup at its
    switch) against a forecast with the timing the robot will actually have.

    It offers the same interface as a trajectory (``q``, ``qd``, ``tcp`` when the wrapped one has it,
    ``t_start``, ``t_end``, ``duration``), for wall times; before ``t_ref`` it holds the pose at ``t_ref``.
    """

    def __init__(self, traj: TrajectoryLike, *, t_ref: float, tau_ref: float, scale: float) -> None:
        if not scale > 0:
            raise ValueError(f"ScaledView needs a positive scale, got {scale}")
        self.traj = traj
        self.t_ref = float(t_ref)
        self.tau_ref = float(tau_ref)
        self.scale = float(scale)

    def _tau(self, t: Any) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return self.tau_ref + self.scale * np.maximum(t - self.t_ref, 0.0)

    @property
    def base_trajectory(self) -> TrajectoryLike:
        """The wrapped trajectory (the planner's compiled check evaluates its knots at :meth:`path_times`)."""
        return self.traj

    def path_times(self, t: np.ndarray) -> np.ndarray:
        """Path times (N,) of ``traj`` at wall times ``t`` (N,)."""
        return self._tau(t)

    @property
    def t_start(self) -> float:
        return self.t_ref

    @property
    def t_end(self) -> float:
        return self.t_ref + max(self.traj.t_end - self.tau_ref, 0.0) / self.scale

    @property
    def duration(self) -> float:
        return self.t_end - self.t_start

    def q(self, t: Any) -> np.ndarray:
        return self.traj.q(self._tau(t))

    def qd(self, t: Any) -> np.ndarray:
        tau = self._tau(t)
        return self.traj.qd(tau) * self.scale

    def tcp(self, t: Any) -> np.ndarray:
        return self.traj.tcp(self._tau(t))  # type: ignore[attr-defined]

    def sample(self, dt_s: float, *, t_from: float | None = None, t_to: float | None = None) -> np.ndarray:
        """Wall times (N,) every ``dt_s`` from ``t_from`` (default ``t_start``) to ``t_to`` (default
        ``t_end``), both ends included."""
        return _sample(self.t_start, self.t_end, dt_s, t_from, t_to)


@dataclass(frozen=True, slots=True)
class SpeedProfile:
    """Speed of each robot part along a trajectory at scale 1, sampled in path time.

    Attributes:
        tau0: Path time of the first sample (s).
        step_s: Sample spacing (s).
        v_mps: (K, L) speed of each part at each sample (m/s).
        window_mps: (K, L) the largest speed of each part from each sample over the following ``window_s``.
        qd_max: (K,) windowed braking joint speed (rad/s;
            :meth:`app.safety.stopping.StoppingModel.braking_speed`), bounds a brake's joint deceleration.
        qd_top: (K,) windowed largest joint speed (rad/s), bounds the joint acceleration of the scale's ramp.
    """

    tau0: float
    step_s: float
    v_mps: np.ndarray
    window_mps: np.ndarray
    qd_max: np.ndarray
    qd_top: np.ndarray

    @classmethod
    def still(cls, tau0: float, n_parts: int) -> SpeedProfile:
        """The profile of a robot that does not move."""
        z = np.zeros((1, n_parts))
        return cls(tau0=tau0, step_s=1.0, v_mps=z, window_mps=z, qd_max=np.zeros(1), qd_top=np.zeros(1))

    @classmethod
    def of(
        cls, traj: TrajectoryLike, geometry: RobotGeometry, *, step_s: float = 0.02, window_s: float = 0.6
    ) -> SpeedProfile:
        t0, t1 = float(traj.t_start), float(traj.t_end)
        n = max(math.ceil((t1 - t0) / step_s) + 1, 2) if t1 > t0 else 2
        taus = t0 + np.arange(n) * step_s
        taus[-1] = min(taus[-1], max(t1, t0))
        q = np.asarray(traj.q(taus), dtype=np.float64).reshape(n, 6)
        qd = np.asarray(traj.qd(taus), dtype=np.float64).reshape(n, 6)
        v = np.asarray(geometry.part_speeds(q, qd), dtype=np.float64).reshape(n, -1)
        jq = np.atleast_1d(UR5E_STOP.braking_speed(qd))
        top = np.abs(qd).max(axis=1)
        w = max(math.ceil(window_s / step_s), 1) + 1
        return cls(
            tau0=t0,
            step_s=step_s,
            v_mps=v,
            window_mps=_forward_max(v, w),
            qd_max=_forward_max(jq, w),
            qd_top=_forward_max(top, w),
        )

    @property
    def n_parts(self) -> int:
        return int(self.v_mps.shape[1])

    def window_at(self, tau: float) -> np.ndarray:
        """(L,) largest speed of each part over the window starting at path time ``tau`` (0 after the end)."""
        i = int((tau - self.tau0) / self.step_s)
        if i >= self.window_mps.shape[0]:
            return np.zeros(self.n_parts)
        i = max(i, 0)
        # the sample before tau may be faster than the one at tau: take both
        return np.maximum(self.window_mps[i], self.window_mps[max(i - 1, 0)])

    def speed_at(self, tau: float) -> np.ndarray:
        """(L,) speed of each part at path time ``tau`` (0 after the end)."""
        x = (tau - self.tau0) / self.step_s
        k = self.v_mps.shape[0]
        if x > k - 1 + 1e-9:
            return np.zeros(self.n_parts)
        i = min(max(int(x), 0), k - 1)
        j = min(i + 1, k - 1)
        w = min(max(x - i, 0.0), 1.0)
        return self.v_mps[i] * (1.0 - w) + self.v_mps[j] * w

    def joint_window_at(self, tau: float) -> float:
        """The braking joint speed (rad/s) over the window starting at path time ``tau`` (0 after the end)."""
        return _window(self.qd_max, self.tau0, self.step_s, tau)

    def top_joint_window_at(self, tau: float) -> float:
        """The largest joint speed (rad/s) over the window starting at path time ``tau`` (0 after the end)."""
        return _window(self.qd_top, self.tau0, self.step_s, tau)


def _window(x: np.ndarray, tau0: float, step_s: float, tau: float) -> float:
    i = int((tau - tau0) / step_s)
    if i >= x.shape[0]:
        return 0.0
    i = max(i, 0)
    return float(max(x[i], x[max(i - 1, 0)]))


def _forward_max(x: np.ndarray, w: int) -> np.ndarray:
    """out[k] = max(x[k : k + w]) along the first axis of (K, ...) x."""
    n = x.shape[0]
    pad = np.concatenate([x, np.full((w - 1, *x.shape[1:]), -np.inf)], axis=0)
    win = np.lib.stride_tricks.sliding_window_view(pad, w, axis=0)[:n]
    return win.max(axis=-1)


def traj_state(traj: TrajectoryLike, t: float) -> tuple[np.ndarray, np.ndarray]:
    """``(q(t), qd(t))`` (6,) each, through the trajectory's one-look-up ``state`` where it has one."""
    state = getattr(traj, "state", None)
    if state is not None:
        q, qd = state(t)
    else:
        q, qd = traj.q(t), traj.qd(t)
    return np.asarray(q, dtype=np.float64).reshape(6), np.asarray(qd, dtype=np.float64).reshape(6)
