"""The paper's replan state machine (section II-B): backup plans under a deadline, emergency plans, the
decision between *Nominal Execution* and *Collision Avoidance*, and speed scaling by separation.

For every new frame at ``T_i`` the :class:`Supervisor`

1. prepares the *backup plan* request from ``s = pi_curr(T_i + D)`` toward the current goal against the
   latest forecast, under the deadline ``D``; its result is usable from ``T_i + D``. Where the robot must
   start moving (at rest, or after an emergency plan) the plan starts from its current position (a plan from
   rest may take ``start_deadline_s``, 3 D by default: the robot stands still meanwhile), and it is executed
   only if the latest forecast predicts no violation anywhere along it (``clear_start``): a robot at rest
   need not set off toward where the person is about to be, it waits and plans again;
2. checks the plan in execution against the *latest* forecast (:meth:`PlannerLike.first_violation`) and the
   robot's parts against the stop distance S_p(0) (ISO/TS 15066, the person's measured speed);
3. decides: *Nominal Execution* (continue; speed scaled by separation), or *Collision Avoidance*: a violation
   predicted after ``T_i + D`` schedules a switch to the backup plan at ``T_i + D`` (an *online replan*); a
   violation before ``T_i + D`` or a violated stop distance stops the robot and switches to the *emergency
   plan* (the person held at the current pose, horizon ``F + D``; a *stop & replan*). A backup that misses
   its deadline, or a planner that raises, takes the emergency path too.

A backup plan of frame ``i`` is used by nothing but the switch that frame ``i``'s decision schedules (later
frames branch from the plan in execution at their own time, and a switch invalidates the backups that
branched from the plan it replaces), so the request goes to the :class:`PlanJobs` only when the decision
schedules that switch: the decisions are those of computing every frame's backup, without the plans nobody
uses (live: on a worker pool, at most ``ceil(D / F)`` in flight; headless: when the switch is due, its
measured compute time charged as if it had started at ``T_i``). The emergency plan is likewise computed when
a stop is decided, from the point where the brake brings the robot to rest.

The reactive baseline is the same machine fed :meth:`HumanForecast.hold` of the current pose.

Execution uses a path-time parameter: the trajectory of the plan in execution is evaluated at ``tau``, which
advances by ``scale * dt``; speed scaling therefore changes the timing along the path, not the path. Where the
robot will be at ``T_i + D`` is predicted with the fastest scale the ramp allows, so that the robot reaches
the branch point of a backup plan at or after ``T_i + D`` and the switch is continuous in position and path
velocity. Every plan is checked against the latest forecast, in wall time with the current scale, before it
is executed: a backup is re-checked at the switch, an emergency plan when the robot has come to rest.

Between frames a *speed governor* keeps ISO/TS 15066's protective separation at every servo tick, per robot
part (capsule): the part's separation to the last seen pose, reduced by the person's worst-case approach
since that frame (:class:`SeparationModel`: their measured speed near the part, speeding up at most at
``human_accel_mps2``) and by the part's own travel, must let the robot brake to rest without the person
coming closer than ``S_p(part speed, person speed)`` at any instant of the braking.

This module is pure: no threads of its own, no clock; time comes in as arguments. One lock makes it safe to
call :meth:`Supervisor.on_frame` and :meth:`Supervisor.servo` from different threads.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np

from app.control.metrics import Method
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame
from app.safety._kernels import governed_scale as _kernel_governed_scale
from app.safety._kernels import max_scale as _kernel_max_scale

log = logging.getLogger(__name__)

SupervisorState = Literal["idle", "nominal", "collision_avoidance", "stopped", "estop", "fault"]
#: Every state a :class:`Supervisor` can be in.
SUPERVISOR_STATES: tuple[SupervisorState, ...] = (
    "idle",
    "nominal",
    "collision_avoidance",
    "stopped",
    "estop",
    "fault",
)
Goal = str | int
SwitchReason = Literal["online_replan", "start", "resume"]

_EPS_SCALE = 1e-6


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


class PlanLike(Protocol):
    times: np.ndarray
    q: np.ndarray
    nodes: np.ndarray


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
    ) -> PlanResultLike: ...

    def emergency(
        self, *, q_start: np.ndarray, t_start: float, forecast: HumanForecast, horizon_s: float
    ) -> PlanResultLike: ...

    def first_violation(
        self, traj: Any, forecast: HumanForecast, *, t_from: float, t_to: float, dt_s: float | None = None
    ) -> float | None: ...


class RobotGeometry(Protocol):
    """The robot's body as ``L`` parts (see :class:`app.control.engine.CellGeometry`: one per capsule)."""

    def part_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """Surface distance (P, L) in m between each part of the robot at ``q`` (6,) and the person in each
        of the poses ``joints`` (P, J, 3)."""
        ...

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """Speed (K, L) in m/s of each part (its fastest point) for ``q``, ``qd`` (K, 6)."""
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
        qd_max: (K,) windowed largest joint speed (rad/s), bounds the joint deceleration of a brake.
    """

    tau0: float
    step_s: float
    v_mps: np.ndarray
    window_mps: np.ndarray
    qd_max: np.ndarray

    @classmethod
    def still(cls, tau0: float, n_parts: int) -> SpeedProfile:
        """The profile of a robot that does not move."""
        z = np.zeros((1, n_parts))
        return cls(tau0=tau0, step_s=1.0, v_mps=z, window_mps=z, qd_max=np.zeros(1))

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
        jq = np.abs(qd).max(axis=1)
        w = max(math.ceil(window_s / step_s), 1) + 1
        return cls(tau0=t0, step_s=step_s, v_mps=v, window_mps=_forward_max(v, w), qd_max=_forward_max(jq, w))

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
        i = int((tau - self.tau0) / self.step_s)
        if i >= self.qd_max.shape[0]:
            return 0.0
        i = max(i, 0)
        return float(max(self.qd_max[i], self.qd_max[max(i - 1, 0)]))


def _forward_max(x: np.ndarray, w: int) -> np.ndarray:
    """out[k] = max(x[k : k + w]) along the first axis of (K, ...) x."""
    n = x.shape[0]
    pad = np.concatenate([x, np.full((w - 1, *x.shape[1:]), -np.inf)], axis=0)
    win = np.lib.stride_tricks.sliding_window_view(pad, w, axis=0)[:n]
    return win.max(axis=-1)


# ----------------------------------------------------------------------------------------------------
# Speed governor: ISO/TS 15066 separation at every servo tick
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SeparationModel:
    """ISO/TS 15066 protective separation, and the braking envelope built on it.

    ``S_p = S_h + S_r + S_s + C + Z_d + Z_r`` with ``S_h = v_h (T_r + T_s)``, ``S_r = v_r T_r``,
    ``S_s = v_r T_s / 2``, where ``v_r`` is the speed of the robot part, ``v_h`` the person's speed toward it
    (ISO/TS 15066 5.5.4.2.3: the measured speed where the system monitors it, as here) and ``T_s`` the
    robot's stopping time *from its current speed*: ``T_s = v_top / stop_decel_mps2`` with ``v_top`` the
    speed of the robot's fastest part (a robot creeping at 1 cm/s stops in milliseconds, not in the 0.2 s
    it needs at 1 m/s). With :class:`app.safety.ssm.SSMParams` (:meth:`from_ssm`):
    ``s0 = C + Z_d + Z_r``, ``T_r = t_reaction_s``.

    The *envelope* answers: how fast may the robot move at separation ``d`` so that, braking now, the
    separation stays at or above ``S_p`` at every instant until it is at rest, while the person approaches
    as fast as a person can: speeding up from ``v_h0`` at ``human_accel_mps2`` to at most
    ``human_speed_max_mps`` (their approach and the robot's own travel both counted)?

    Attributes:
        s0_m: ``C + Z_d + Z_r`` (m).
        t_reaction_s: ``T_r`` (s).
        stop_decel_mps2: The robot's stopping deceleration for ``T_s`` (m/s^2).
        human_speed_max_mps: Fastest approach of a person (m/s).
        human_accel_mps2: Fastest change of a person's speed (m/s^2).
    """

    s0_m: float = 0.11
    t_reaction_s: float = 0.1
    stop_decel_mps2: float = 2.0
    human_speed_max_mps: float = 2.0
    human_accel_mps2: float = 8.0
    _kernel_params: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        names = ("s0_m", "t_reaction_s", "stop_decel_mps2", "human_speed_max_mps", "human_accel_mps2")
        for name in names:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"SeparationModel.{name} must be finite and >= 0, got {v}")
        if self.stop_decel_mps2 <= 0:
            raise ValueError("SeparationModel.stop_decel_mps2 must be > 0")
        object.__setattr__(self, "_kernel_params", np.array([float(getattr(self, n)) for n in names]))

    @classmethod
    def from_ssm(
        cls,
        params: Any,
        *,
        human_speed_max_mps: float = 2.0,
        human_accel_mps2: float = 8.0,
        stop_decel_mps2: float = 2.0,
    ) -> SeparationModel:
        """From :class:`app.safety.ssm.SSMParams` (``C``, ``Z_d``, ``Z_r``, ``T_r``)."""
        return cls(
            s0_m=float(params.intrusion_m + params.z_human_m + params.z_robot_m),
            t_reaction_s=float(params.t_reaction_s),
            stop_decel_mps2=stop_decel_mps2,
            human_speed_max_mps=human_speed_max_mps,
            human_accel_mps2=human_accel_mps2,
        )

    def sp(self, v_part: Any, v_top: Any, v_human: Any) -> Any:
        """``S_p`` (m) of a part moving at ``v_part`` on a robot whose fastest part moves at ``v_top``, the
        person approaching at ``v_human`` (arrays broadcast)."""
        v_part = np.maximum(v_part, 0.0)
        t_s = np.maximum(v_top, 0.0) / self.stop_decel_mps2
        t_r = self.t_reaction_s
        return self.s0_m + np.maximum(v_human, 0.0) * (t_r + t_s) + v_part * (t_r + 0.5 * t_s)

    def required(self, v_robot_mps: float, v_human_mps: float = 0.0) -> float:
        """``S_p`` (m) of the robot's fastest part."""
        return float(self.sp(v_robot_mps, v_robot_mps, v_human_mps))

    def human_approach(self, v_h0: Any, dt: Any) -> tuple[np.ndarray, np.ndarray]:
        """Worst-case approach distance (m) and speed (m/s) of the person ``dt`` (s) after moving at
        ``v_h0`` toward the robot (both broadcast)."""
        v_h0 = np.asarray(v_h0, dtype=np.float64)
        dt = np.maximum(np.asarray(dt, dtype=np.float64), 0.0)
        vmax = np.maximum(self.human_speed_max_mps, v_h0)
        a = self.human_accel_mps2
        if a <= 0:
            return v_h0 * dt, np.broadcast_to(v_h0, np.broadcast(v_h0, dt).shape).copy()
        t1 = (vmax - v_h0) / a
        acc = np.minimum(dt, t1)
        dist = v_h0 * acc + 0.5 * a * acc**2 + vmax * np.maximum(dt - t1, 0.0)
        return dist, np.minimum(v_h0 + a * dt, vmax)

    def max_speed(
        self, separation_m: Any, *, v_human_mps: Any, decel_mps2: Any, v_cap_mps: float = 3.0
    ) -> Any:
        """Largest safe speed (m/s) of a robot moving as one part at ``separation_m`` with the person
        approaching at ``v_human_mps`` now, braking at ``decel_mps2`` (0 when even a creeping robot is not
        safe). Arguments broadcast; a float for scalar arguments."""
        d, vh0, a = np.broadcast_arrays(
            np.asarray(separation_m, dtype=np.float64),
            np.asarray(v_human_mps, dtype=np.float64),
            np.maximum(np.asarray(decel_mps2, dtype=np.float64), 1e-3),
        )
        shape = d.shape
        d, vh0, a = d.reshape(-1, 1, 1), vh0.reshape(-1, 1, 1), a.reshape(-1, 1, 1)
        v = np.linspace(0.0, v_cap_mps, _ENV_NV)[None, :, None]
        t = _ENV_U[None, None, :] * v / a
        x_h, v_h = self.human_approach(vh0, t)
        travel = v * t - 0.5 * a * t**2
        vt = v - a * t
        need = self.sp(vt, vt, v_h)
        ok = np.all(d - x_h - travel - need >= 0.0, axis=2)  # (P, NV)
        ok &= np.isfinite(d[:, :, 0]) | (d[:, :, 0] > 0)
        n_ok = np.cumprod(ok, axis=1).sum(axis=1)  # leading feasible speeds
        out = np.where(n_ok > 0, v[0, np.maximum(n_ok - 1, 0), 0], 0.0)
        out = np.where(~np.isfinite(d[:, 0, 0]) & (d[:, 0, 0] > 0), v_cap_mps, out)
        out = out.reshape(shape)
        return float(out) if out.ndim == 0 else out

    def max_scale(
        self,
        separation_m: np.ndarray,
        *,
        v_human_mps: np.ndarray,
        v_parts_mps: np.ndarray,
        rate: float,
        lo: float = 0.0,
        hi: float = 1.0,
    ) -> float:
        """Largest path-speed scale in [0, 1] that is safe for every part: part i moves at
        ``s * v_parts_mps[i]`` and a brake lowers the scale at ``rate`` (1/s), so every part stops after
        ``s / rate``. Arrays (L,) (the parts that move).

        Only scales in ``[lo, hi]`` are examined (the grid's and both ends; the servo passes the range it
        can reach within one tick): the answer is the largest of them up to which every one is safe, ``hi``
        at most, and 0 when ``lo`` is not safe. Compiled (:func:`app.safety._kernels.max_scale`); the same
        numbers as :meth:`max_scale_reference`."""
        return float(
            _kernel_max_scale(
                np.ascontiguousarray(separation_m, dtype=np.float64).reshape(-1),
                np.ascontiguousarray(v_human_mps, dtype=np.float64).reshape(-1),
                np.ascontiguousarray(v_parts_mps, dtype=np.float64).reshape(-1),
                float(rate),
                float(lo),
                float(hi),
                _SCALES,
                _ENV_U,
                self._kernel_params,
            )
        )

    def max_scale_reference(
        self,
        separation_m: np.ndarray,
        *,
        v_human_mps: np.ndarray,
        v_parts_mps: np.ndarray,
        rate: float,
        lo: float = 0.0,
        hi: float = 1.0,
    ) -> float:
        """:meth:`max_scale` in NumPy over the whole envelope at once (the reference of the tests)."""
        d1 = np.asarray(separation_m, dtype=np.float64)
        vh1 = np.asarray(v_human_mps, dtype=np.float64)
        vp1 = np.asarray(v_parts_mps, dtype=np.float64)
        if d1.size == 0:
            return 1.0
        vtop = float(vp1.max())
        lo, hi = max(float(lo), 0.0), min(float(hi), 1.0)
        # quick accept (most ticks): every term at its largest over a brake from the highest scale asked for
        t_b = hi / max(rate, 1e-6)
        x_b, v_b = self.human_approach(vh1, t_b)
        worst = self.sp(hi * vp1, hi * vtop, v_b) + x_b + hi * vp1 * t_b
        if bool(np.all(d1 >= worst)):
            return hi
        inside = (_SCALES - lo > 0.0) & (_SCALES - hi < 0.0)
        scales = _SCALES[inside]
        scales = np.concatenate([[lo], scales, [hi]]) if hi > lo else np.array([lo])
        d, vh0, vp = d1[:, None, None], vh1[:, None, None], vp1[:, None, None]
        sc = scales[None, :, None]
        t = _ENV_U[None, None, :] * sc / max(rate, 1e-6)
        x_h, v_h = self.human_approach(vh0, t)
        a = rate * vp
        v = sc * vp
        travel = v * t - 0.5 * a * t**2
        s_t = sc - rate * t  # the scale during the brake
        need = self.sp(s_t * vp, s_t * vtop, v_h)
        ok = np.all(d - x_h - travel - need >= 0.0, axis=2).all(axis=0)  # (NS,) every part
        n_ok = int(np.cumprod(ok).sum())
        return float(scales[n_ok - 1]) if n_ok > 0 else 0.0


@dataclass(frozen=True, slots=True)
class SpeedScaleLaw:
    """The ISO/TS 15066 speed-scaling law (:func:`app.safety.ssm.speed_scale`) as the speed governor
    applies it per servo tick: the smallest scale over the moving parts.

    Attributes:
        params: :class:`app.safety.ssm.SSMParams` (``T_r``, ``T_s``, ``C``, ``Z_d``, ``Z_r``).
        kernel_params: ``(T_r + T_s, C + Z_d + Z_r, T_r + T_s / 2)`` as the compiled governor reads them.
    """

    params: Any
    kernel_params: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        p = self.params
        kernel = np.array([p.t_reaction_s + p.t_stop_s, p.constant_m, p.robot_time_s], dtype=np.float64)
        object.__setattr__(self, "kernel_params", kernel)

    def __call__(self, separation_m: np.ndarray, v_nominal_mps: np.ndarray, v_human_mps: np.ndarray) -> float:
        """The smallest scale over parts (L,) (1 for no part), in NumPy: the compiled governor's reference."""
        from app.safety.ssm import speed_scale

        d = np.asarray(separation_m, dtype=np.float64)
        if d.size == 0:
            return 1.0
        return float(np.min(speed_scale(d, v_nominal_mps, self.params, v_human_mps=v_human_mps)))


_NO_LAW = np.zeros(0)
_SCALES = np.linspace(0.0, 1.0, 41)
_ENV_NV = 97
_ENV_U = np.linspace(0.0, 1.0, 25)[:-1]  # instants of the braking (its end: the robot is at rest)


# ----------------------------------------------------------------------------------------------------
# Plan jobs: backup plans under the deadline
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class BackupRequest:
    """A backup plan to compute for frame ``key``.

    Attributes:
        key: Frame sequence number.
        t_request: ``T_i``: when the frame arrived (s).
        t_start: When the plan starts (``T_i + D``, or later when the robot holds until then) (s).
        q_start: (6,) start configuration ``pi_curr(T_i + D)``.
        qd_start: (6,) path velocity of the plan in execution at the branch point (scale 1), so that the
            new trajectory continues it.
        goal: Roadmap goal (station name or node index).
        forecast: The forecast of frame ``key``.
        deadline_s: Compute-time budget of this plan: D, or the start deadline for a robot at rest.
    """

    key: int
    t_request: float
    t_start: float
    q_start: np.ndarray
    qd_start: np.ndarray
    goal: Goal
    forecast: HumanForecast
    deadline_s: float | None = None


OutcomeStatus = Literal["ok", "failed", "deadline_miss", "error", "skipped"]


@dataclass(frozen=True, slots=True)
class PlanOutcome:
    """What became of a plan request.

    Attributes:
        status: ``ok``; ``failed`` (the planner found no plan); ``deadline_miss`` (slower than D);
            ``error`` (the planner raised); ``skipped`` (no worker free, or never requested).
        compute_s: Measured compute time (s) of the planner call and the trajectory building.
        traj: The trajectory (when ``ok``).
        profile: Its speed profile (when ``ok``).
        plan: The planner's plan (when ``ok``).
        reason: The planner's reason or the error message.
    """

    status: OutcomeStatus
    compute_s: float = 0.0
    traj: TrajectoryLike | None = None
    profile: SpeedProfile | None = None
    plan: Any = None
    reason: str = ""


class PlanJobs(Protocol):
    """Runs backup plans. ``submit`` at ``T_i``; ``take`` at or after ``T_i + D`` (never blocks long)."""

    def submit(self, request: BackupRequest) -> None: ...

    def take(self, key: int, request: BackupRequest | None = None) -> PlanOutcome: ...

    def peek(self, key: int) -> PlanOutcome | None:
        """The outcome if it is already known without computing anything, else None."""
        ...

    def close(self) -> None: ...


class BackupComputer:
    """Computes one backup plan: planner call, trajectory, speed profile; times the whole of it."""

    def __init__(
        self,
        planner: PlannerLike,
        make_trajectory: MakeTrajectory,
        geometry: RobotGeometry,
        *,
        deadline_s: float,
        workers: int,
        timer: Callable[[], float] = time.perf_counter,
        profile_window_s: float = 0.6,
    ) -> None:
        self.planner = planner
        self.make_trajectory = make_trajectory
        self.geometry = geometry
        self.deadline_s = float(deadline_s)
        self.workers = int(workers)
        self.timer = timer
        self.profile_window_s = profile_window_s
        #: Give the planner the deadline (live, measured headless); False when compute times are fixed.
        self.enforce_deadline = True

    def __call__(self, req: BackupRequest) -> PlanOutcome:
        """Plan, build the trajectory and its speed profile; ``ok`` or ``deadline_miss`` by the measured
        compute time (see :meth:`judge`)."""
        return self.judge(self.compute_raw(req), None, deadline_s=req.deadline_s)

    def compute_raw(self, req: BackupRequest) -> PlanOutcome:
        """The plan with its measured compute time, not yet judged against the deadline."""
        t0 = self.timer()
        try:
            res = self.planner.plan(
                q_start=req.q_start,
                t_start=req.t_start,
                goal=req.goal,
                forecast=req.forecast,
                workers=self.workers,
                deadline_s=(req.deadline_s or self.deadline_s) if self.enforce_deadline else None,
                qd0=req.qd_start,
            )
            if not res.ok or res.plan is None:
                return PlanOutcome("failed", compute_s=self.timer() - t0, reason=str(res.reason))
            traj = self.make_trajectory(res.plan, req.qd_start)
            prof = SpeedProfile.of(traj, self.geometry, window_s=self.profile_window_s)
        except Exception as exc:  # a planner fault must take the emergency path, never kill the loop
            log.exception("backup plan for frame %d raised", req.key)
            return PlanOutcome("error", compute_s=self.timer() - t0, reason=f"{type(exc).__name__}: {exc}")
        dt = self.timer() - t0
        return PlanOutcome("ok", compute_s=dt, traj=traj, profile=prof, plan=res.plan, reason=str(res.reason))

    def judge(
        self, out: PlanOutcome, compute_s: float | None, *, deadline_s: float | None = None
    ) -> PlanOutcome:
        """Apply the deadline (``deadline_s``, default D): a plan slower than it (by ``compute_s`` when
        given, else its measured time) is a ``deadline_miss``, whatever it found; so is a search the
        planner cut at the deadline."""
        c = out.compute_s if compute_s is None else float(compute_s)
        limit = self.deadline_s if deadline_s is None else float(deadline_s)
        if out.status in ("ok", "failed") and (c > limit or out.reason == "deadline"):
            return PlanOutcome("deadline_miss", compute_s=c, reason=f"{c * 1e3:.1f} ms > D ({out.reason})")
        return PlanOutcome(out.status, c, out.traj, out.profile, out.plan, out.reason)


class InlinePlanJobs:
    """Headless plan jobs: a backup plan is computed only when its own frame's decision consumes it.

    A backup plan of frame ``i`` is used by nothing but the switch that frame ``i``'s decision schedules
    at ``T_i + D`` (later frames branch from the plan in execution at their own time, and a switch
    invalidates backups that branched from the plan it replaces). Computing it when that switch is due and
    charging its measured compute time as if it had started at ``T_i`` therefore gives the same decisions as
    computing every backup eagerly, at a fraction of the cost: a plan slower than ``D`` is a deadline miss,
    exactly as in live mode.

    Args:
        compute: The backup computer.
        fixed_compute_s: When given, the compute time charged for every plan instead of the measured one
            (makes a headless run fully deterministic; used in tests).
        keep: How many pending requests to keep (older ones are dropped: their switch can no longer occur).
    """

    def __init__(
        self, compute: BackupComputer, *, fixed_compute_s: float | None = None, keep: int = 16
    ) -> None:
        self.compute = compute
        self.fixed_compute_s = fixed_compute_s
        compute.enforce_deadline = fixed_compute_s is None
        self._pending: dict[int, BackupRequest] = {}
        self._keep = keep

    def submit(self, request: BackupRequest) -> None:
        self._pending[request.key] = request
        if len(self._pending) > self._keep:
            for k in sorted(self._pending)[: len(self._pending) - self._keep]:
                del self._pending[k]

    def take(self, key: int, request: BackupRequest | None = None) -> PlanOutcome:
        req = self._pending.pop(key, None) or request
        if req is None:
            return PlanOutcome("skipped", reason=f"no backup request for frame {key}")
        return self.compute.judge(
            self.compute.compute_raw(req), self.fixed_compute_s, deadline_s=req.deadline_s
        )

    def peek(self, key: int) -> PlanOutcome | None:
        return None

    def close(self) -> None:
        self._pending.clear()


# ----------------------------------------------------------------------------------------------------
# The supervisor
# ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SupervisorConfig:
    """Parameters of the state machine. D, F and the workers come from :class:`app.config.Settings`.

    Attributes:
        method: ``proactive`` (the predictor's forecast) or ``reactive`` (the current pose held).
        deadline_s: D, the backup-plan deadline (s).
        start_deadline_s: Deadline of a plan that starts the robot from rest (default 3 D): the robot stands
            still until the plan starts, so a longer search costs waiting time only, not safety.
        frame_period_s: F, the camera frame period (s).
        planner_workers: Workers per plan (parallel A*).
        brake_decel_mps2: Deceleration of the robot's fastest point when braking (m/s^2).
        brake_joint_decel: Largest joint deceleration when braking (rad/s^2).
        scale_up_rate: Largest increase of the speed scale per second (1/s).
        tracking_margin_m: Tracking error of a frame: subtracted from measured separations and used as the
            margin of the held pose (reactive forecast, emergency plan).
        human_speed_window_s: Window (s) over which the person's speed is measured.
        near_band_m: The person's parts within this much of being the nearest to a robot part count for
            the speed of the person near that part (m).
        retry_after_s: After a failed plan to start (or resume) moving, the next attempt waits this long (s).
        clear_start: A plan that starts the robot from rest (or resumes it) is executed only if the latest
            forecast predicts no violation anywhere along it (timed at ``check_min_scale``); else the robot
            stays at rest and plans again after ``retry_after_s``. False: only a violation before
            ``T_i + D`` forbids it, as for a backup that replaces a plan in execution.
        resume_travel_m: After a stop & replan, the robot counts as under way again (a new encounter can
            stop it again) once it has moved this far (m).
        check_dt_s: Time step of the checks of a plan against a forecast (s).
        check_min_scale: Scale floor used to time the plan in execution for checks when the robot is slowed
            or stopped (the robot is assumed to go at least this fast when it resumes).
        profile_window_s: Look-ahead of the speed governor along the path (s).
        emergency_horizon_s: Horizon of the emergency plan; default F + D.
    """

    method: Method = "proactive"
    deadline_s: float = 0.1
    start_deadline_s: float | None = None
    frame_period_s: float = 1.0 / 30.0
    planner_workers: int = 1
    brake_decel_mps2: float = 3.0
    brake_joint_decel: float = 3.0
    scale_up_rate: float = 4.0
    tracking_margin_m: float = 0.02
    human_speed_window_s: float = 0.1
    near_band_m: float = 0.25
    retry_after_s: float = 0.2
    clear_start: bool = True
    resume_travel_m: float = 0.03
    check_dt_s: float = 0.04
    check_min_scale: float = 0.5
    profile_window_s: float = 0.6
    emergency_horizon_s: float | None = None

    def __post_init__(self) -> None:
        if self.method not in ("proactive", "reactive"):
            raise ValueError(f"method must be 'proactive' or 'reactive', got {self.method!r}")
        if self.deadline_s <= 0 or self.frame_period_s <= 0:
            raise ValueError("deadline_s and frame_period_s must be positive")

    @property
    def max_jobs(self) -> int:
        """Backup jobs in flight at most: ceil(D / F)."""
        return max(1, math.ceil(self.deadline_s / self.frame_period_s - 1e-9))

    @property
    def start_deadline(self) -> float:
        return 3.0 * self.deadline_s if self.start_deadline_s is None else self.start_deadline_s

    @property
    def emergency_horizon(self) -> float:
        if self.emergency_horizon_s is not None:
            return self.emergency_horizon_s
        return self.frame_period_s + self.deadline_s


@dataclass(frozen=True, slots=True)
class ServoCommand:
    """What the robot is told at one servo tick.

    Attributes:
        t: Time of the tick (s).
        q: (6,) joint positions (rad).
        qd: (6,) joint velocities (rad/s).
        scale: Speed scale in [0, 1] applied along the path.
        hold: True when the robot is meant to stand still.
    """

    t: float
    q: np.ndarray
    qd: np.ndarray
    scale: float
    hold: bool


@dataclass(frozen=True, slots=True)
class FrameDecision:
    """The outcome of one frame's decision (for logs, tests and the loop benchmark).

    Attributes:
        action: ``nominal``, ``online_replan`` (switch scheduled), ``stop_replan``, ``start`` (switch
            scheduled from rest), ``resume`` (switch scheduled after an emergency plan), ``hold`` (nothing to
            do), ``skipped`` (the state changed while deciding).
        violation_t: Predicted violation time of the plan in execution, if any (s).
        separation_m: Measured separation minus the tracking margin (m).
        decide_s: Compute time of the decision itself (s), without the backup plan's search.
    """

    action: str
    violation_t: float | None
    separation_m: float
    decide_s: float


@dataclass
class _Active:
    traj: TrajectoryLike
    profile: SpeedProfile
    plan_id: int
    kind: Literal["hold", "plan", "emergency"]
    complete: bool
    goal: Goal | None
    checked_seq: int

    def under_way(self, tau: float) -> bool:
        """A plan (not a hold) with path left after path time ``tau``."""
        return self.kind != "hold" and tau < self.traj.t_end


@dataclass
class _Pending:
    key: int
    t_switch: float
    tau_branch: float
    plan_id: int
    reason: SwitchReason
    violation_t: float | None
    request: BackupRequest | None = None
    outcome: PlanOutcome | None = None
    checked_seq: int = -1

    @property
    def from_rest(self) -> bool:
        """The switch sets a robot at rest moving (a start, or a resume after a stop)."""
        return self.reason in ("start", "resume")


@dataclass
class _Brake:
    t0: float
    tau0: float
    s0: float
    rate: float
    t_stop: float
    tau_stop: float
    reason: str
    emergency: _Active | None = None
    emergency_ready_t: float = math.inf
    emergency_tried: bool = False


@dataclass
class SupervisorCounters:
    """Running totals of one trial."""

    stop_replans: int = 0
    online_replans: int = 0
    deadline_misses: int = 0
    emergency_plans: int = 0
    plan_failures: int = 0
    plans_computed: int = 0
    planning_times_s: list[float] = field(default_factory=list)
    stale_stops: int = 0
    frames: int = 0
    state_time_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(SUPERVISOR_STATES, 0.0))
    #: time under way on a plan (scale above zero, brakes included) and the integral of the scale over it
    moving_time_s: float = 0.0
    scale_time_s: float = 0.0


@dataclass(frozen=True, slots=True)
class SupervisorStatus:
    """An immutable read-out of the supervisor, for snapshots.

    Attributes:
        t: Time of the last servo tick (s).
        state: One of :data:`SUPERVISOR_STATES`.
        scale: Current speed scale.
        separation_m: Last measured separation (m), inf when no person was seen.
        required_separation_m: S_p for the robot's current speed (m).
        q: (6,) last commanded configuration.
        plan: The trajectory in execution (None when holding).
        plan_tau: Path time in it.
        backup: The trajectory of a pending switch, when known.
        stale: The stream is stale (the robot is held).
        estopped: E-stop latched.
    """

    t: float
    state: SupervisorState
    scale: float
    separation_m: float
    required_separation_m: float
    q: np.ndarray
    plan: TrajectoryLike | None
    plan_tau: float
    backup: TrajectoryLike | None
    stale: bool
    estopped: bool


EventSink = Callable[[float, str, dict[str, Any]], None]


class Supervisor:
    """The replan state machine of one robot. See the module docstring.

    Args:
        planner: Plans (``plan``, ``emergency``) and checks (``first_violation``).
        geometry: Separation and point speeds of the robot.
        jobs: Runs backup plans (:class:`InlinePlanJobs` headless, a worker pool live).
        make_trajectory: ``(plan, qd0) -> trajectory``.
        separation: ISO/TS 15066 S_p and the braking envelope.
        speed_scale: The ISO/TS 15066 speed-scaling law at the person's measured speed, applied to the
            moving parts (None: the braking envelope alone limits the speed).
        config: Parameters.
        q0: (6,) initial configuration; the robot holds there.
        t0: Initial time (s).
        on_event: ``(t, kind, payload)`` for every event (kinds of :data:`app.control.metrics.EVENT_KINDS`).
        timer: Monotonic timer for compute times (the emergency plan's).
    """

    def __init__(
        self,
        *,
        planner: PlannerLike,
        geometry: RobotGeometry,
        jobs: PlanJobs,
        make_trajectory: MakeTrajectory,
        separation: SeparationModel,
        speed_scale: SpeedScaleLaw | None = None,
        config: SupervisorConfig,
        q0: np.ndarray,
        t0: float = 0.0,
        on_event: EventSink | None = None,
        timer: Callable[[], float] = time.perf_counter,
    ) -> None:
        q0 = np.asarray(q0, dtype=np.float64)
        if q0.shape != (6,):
            raise ValueError(f"q0 must have shape (6,), got {q0.shape}")
        self.planner = planner
        self.geometry = geometry
        self.jobs = jobs
        self.make_trajectory = make_trajectory
        self.ssm = separation
        self.speed_scale_law = speed_scale
        self.config = config
        self.on_event = on_event
        self.timer = timer
        self.counters = SupervisorCounters()
        self.n_parts = int(np.asarray(geometry.part_speeds(q0[None], np.zeros((1, 6)))).shape[-1])
        self._lock = threading.RLock()
        self._plan_ids = 0
        self._generation = 0
        self._t = float(t0)
        self._tau = float(t0)
        self._s = 0.0
        self._q_cmd = q0.copy()
        self._active = self._hold(q0, t0)
        self._pending: _Pending | None = None
        self._brake: _Brake | None = None
        self._goal: Goal | None = None
        self._not_before = -math.inf
        self._arrived: Goal | None = None
        self._forecast: HumanForecast | None = None
        self._frame: HumanFrame | None = None
        self._seq = -1
        # separation bookkeeping for the governor
        L = self.n_parts
        self._sep_m = np.full(L, math.inf)  # per robot part, minus the tracking margin
        self._sep_person_t = -math.inf  # time of the frame the separation was measured on
        self._v_h0 = np.zeros(L)  # the person's approach speed per part, measured over a window...
        self._v_h_t = -math.inf  # ...whose middle is this
        self._x_h0 = np.zeros(L)  # worst-case approach from the middle of that window to the frame
        self._history: deque[HumanFrame] = deque(maxlen=16)
        self._travel_m = np.zeros(L)  # travel of each part since the separation was measured (bound, m)
        self._v_cmd = np.zeros(L)  # speed bound of each part over the last tick (m/s)
        self._v_inst = np.zeros(L)  # speed of each part along the path at the last tick (m/s)
        self._stale = False
        self._estop = False
        self._fault = False
        self._stopped_latch = False
        self._moved_since_stop = 0.0
        self._retry_after = -math.inf
        self._state: SupervisorState = "idle"
        self._recent_decide_s: deque[float] = deque(maxlen=256)

    # ------------------------------------------------------------------------------------------------
    # task interface
    # ------------------------------------------------------------------------------------------------

    def set_goal(self, goal: Goal | None, *, not_before: float = -math.inf) -> None:
        """Go to ``goal`` next, leaving no earlier than ``not_before`` (s); None: stay where you are."""
        with self._lock:
            self._goal = goal
            self._not_before = float(not_before)
            self._arrived = None

    @property
    def goal(self) -> Goal | None:
        return self._goal

    def take_arrival(self) -> Goal | None:
        """The goal reached since the last call (once), else None."""
        with self._lock:
            g, self._arrived = self._arrived, None
            return g

    @property
    def state(self) -> SupervisorState:
        return self._state

    @property
    def estopped(self) -> bool:
        return self._estop

    @property
    def latest_forecast(self) -> HumanForecast | None:
        return self._forecast

    # ------------------------------------------------------------------------------------------------
    # faults
    # ------------------------------------------------------------------------------------------------

    def set_stale(self, stale: bool, t: float) -> None:
        """The stream went stale (no valid frame for the watchdog's timeout) or resumed. While stale the
        robot brakes to rest and stays there; it resumes through the next frame's decision."""
        with self._lock:
            if stale and not self._stale:
                self.counters.stale_stops += 1
                self._emit(t, "stale_stream", {"age_s": round(t - self._sep_person_t, 4)})
                self._pending = None
            elif not stale and self._stale:
                self._emit(t, "stream_resumed", {})
            self._stale = stale

    def estop(self, t: float, *, source: str = "api") -> None:
        """Latch the E-stop: the robot is held (the runtime also stops the robot); needs :meth:`reset`."""
        with self._lock:
            if not self._estop:
                self._emit(t, "estop", {"source": source})
            self._estop = True
            self._pending = None
            self._brake = None
            self._s = 0.0
            self._activate_hold(self._q_cmd, t)

    def reset(self, t: float, q: np.ndarray) -> None:
        """Clear an E-stop or fault; the robot holds at ``q`` (6,) and plans from there on the next frame."""
        with self._lock:
            self._estop = False
            self._fault = False
            self._pending = None
            self._brake = None
            self._s = 0.0
            self._q_cmd = np.asarray(q, dtype=np.float64).reshape(6).copy()
            self._activate_hold(self._q_cmd, t)
            self._stopped_latch = False

    def fault(self, t: float, message: str) -> None:
        """The robot is lost: stop planning and hold (the runtime ends the trial)."""
        with self._lock:
            if not self._fault:
                self._emit(t, "robot_fault", {"message": message})
            self._fault = True
            self._pending = None
            self._brake = None
            self._s = 0.0

    # ------------------------------------------------------------------------------------------------
    # frames: backup request, checks, decision
    # ------------------------------------------------------------------------------------------------

    def on_frame(self, frame: HumanFrame, forecast: HumanForecast, *, t_now: float) -> FrameDecision:
        """Process a new frame ``frame`` (validated) with the forecast of the method, at time ``t_now``
        (``T_i``, the frame's arrival on the runtime clock)."""
        c0 = self.timer()
        cfg = self.config
        if frame.joints.shape != (NUM_JOINTS, 3):
            raise ValueError(f"frame joints must be ({NUM_JOINTS}, 3), got {frame.joints.shape}")
        with self._lock:
            self._seq += 1
            seq = self._seq
            self.counters.frames += 1
            self._forecast = forecast
            self._frame = frame
            q_now = self._q_cmd.copy()
            gen = self._generation
            active = self._active
            tau, s = self._tau, self._s
            travel0 = self._travel_m.copy()
        # separation of each robot part now (robot at its last commanded pose vs the person as seen), and
        # the person's approach speed: how fast their motion closed the distance over the last window
        old = self._older_frame(frame.t - cfg.human_speed_window_s)
        if old is not None:
            # the person's directed speed toward each part: the fastest approach of the body parts that are
            # (nearly) the nearest to it (over all of them, so it does not jump when the nearest pair changes)
            sep_parts, v_h0 = self.geometry.near_person(
                q_now, frame.joints, old.joints, frame.t - old.t, band_m=cfg.near_band_m
            )
            sep_parts = np.asarray(sep_parts, dtype=np.float64) - cfg.tracking_margin_m
            v_h0 = np.asarray(v_h0, dtype=np.float64)
            t_mid = 0.5 * (frame.t + old.t)
        else:  # no history yet: assume the fastest approach
            d = np.asarray(self.geometry.part_separations(q_now, frame.joints[None]), dtype=np.float64)
            sep_parts = d[0] - cfg.tracking_margin_m
            v_h0, t_mid = np.full(self.n_parts, self.ssm.human_speed_max_mps), frame.t
        sep = float(sep_parts.min())
        self._history.append(frame)
        with self._lock:
            self._sep_m = sep_parts
            self._sep_person_t = frame.t
            self._v_h0 = v_h0
            self._v_h_t = t_mid
            self._x_h0 = np.asarray(self.ssm.human_approach(v_h0, frame.t - t_mid)[0], dtype=np.float64)
            self._travel_m = np.maximum(self._travel_m - travel0, 0.0)  # travel since q_now was read
            if self._estop or self._fault:
                return self._done("hold", None, sep, c0)
            if self._stale:
                return self._done("hold", None, sep, c0)
            goal = self._goal
        T = float(t_now)
        D = cfg.deadline_s

        # 1. the backup request: from pi_curr(T_i + D), or from rest where the robot must start moving
        # (it is handed to the plan jobs when this frame's decision schedules a switch to it: a backup plan
        # is consumed by nothing but the switch its own frame schedules, so the others need not run)
        req = None
        if goal is not None and self._brake is None:
            req = self._branch_request(seq, T, goal, forecast, active, tau, s)

        # 2. check the plan in execution against the latest forecast (outside the lock: it takes a while)
        moving_plan = active.under_way(tau)
        t_v: float | None = None
        if moving_plan:
            view = ScaledView(active.traj, t_ref=T, tau_ref=tau, scale=max(s, cfg.check_min_scale))
            t_v = self._first_violation(view, forecast, T, view.t_end)
        # the stop distance: a part that is to move is within S_p(0) of the person (at their measured speed;
        # the speed governor allows for what they may do before the next frame)
        to_move = active.profile.window_at(tau) > 1e-6
        stop_distance = bool(np.any(to_move & (sep_parts <= self.ssm.s0_m + self.ssm.t_reaction_s * v_h0)))

        # 3. pre-check a finished backup of the pending switch against this (latest) forecast
        with self._lock:
            pend = self._pending
        if pend is not None and pend.outcome is None:
            out = self.jobs.peek(pend.key)
            if out is not None:
                with self._lock:
                    if self._pending is pend:
                        pend.outcome = out
        if pend is not None and pend.outcome is not None and pend.outcome.status == "ok":
            ok = self._backup_passes(pend, pend.outcome, T, tau, s, forecast) is None
            with self._lock:
                if self._pending is pend:
                    pend.checked_seq = seq if ok else -2

        # 4. decide
        with self._lock:
            if gen != self._generation:
                return self._done("skipped", t_v, sep, c0)
            if self._brake is not None:
                return self._done("hold", t_v, sep, c0)
            if moving_plan and (stop_distance or (t_v is not None and t_v <= T + D)):
                pend = self._pending
                if (
                    not stop_distance
                    and pend is not None
                    and pend.plan_id == active.plan_id
                    and t_v is not None
                    and pend.t_switch < t_v
                    and pend.tau_branch <= active.traj.t_end
                ):
                    return self._done("nominal", t_v, sep, c0)  # the scheduled switch comes first
                if self._stopped_latch:
                    # stopped for this already and not really under way again (the speed governor keeps
                    # a creeping robot safe): one stop & replan per encounter
                    self._set_state("stopped", T)
                    return self._done("hold", t_v, sep, c0)
                reason = "stop_distance" if stop_distance else "predicted_violation"
                self._stop_and_replan(T, reason=reason, violation_t=t_v)
                decision = "stop_replan"
            elif moving_plan and t_v is not None:
                pend = self._pending
                if pend is not None and pend.plan_id == active.plan_id and pend.t_switch < t_v:
                    return self._done("online_replan", t_v, sep, c0)
                if req is None:
                    self._stop_and_replan(T, reason="no_backup", violation_t=t_v)
                    decision = "stop_replan"
                else:
                    self._schedule(req[0], req[1], active, "online_replan", t_v)
                    self._set_state("collision_avoidance", T)
                    decision = "online_replan"
            elif active.kind == "hold" or not active.complete:
                if goal is None or req is None:
                    return self._done("hold", t_v, sep, c0)
                if self._pending is not None and self._pending.plan_id == active.plan_id:
                    return self._done("hold", t_v, sep, c0)
                if self._retry_after > T:  # the last start/resume plan failed: give the scene time
                    return self._done("hold", t_v, sep, c0)
                reason_sw: SwitchReason = "start" if active.kind == "hold" else "resume"
                self._schedule(req[0], req[1], active, reason_sw, None)
                decision = reason_sw
            else:
                if self._state in ("collision_avoidance", "stopped") and self._pending is None:
                    self._set_state("nominal", T)
                decision = "nominal"
        brake = self._brake
        if decision == "stop_replan" and brake is not None:
            self._plan_emergency(brake, frame, gen_after=self._generation)
        return self._done(decision, t_v, sep, c0)

    def _done(self, action: str, t_v: float | None, sep: float, c0: float) -> FrameDecision:
        dt = self.timer() - c0
        self._recent_decide_s.append(dt)
        return FrameDecision(action, t_v, sep, dt)

    def _first_violation(
        self, traj: Any, forecast: HumanForecast, t_from: float, t_to: float
    ) -> float | None:
        try:
            return self.planner.first_violation(
                traj, forecast, t_from=t_from, t_to=max(t_to, t_from), dt_s=self.config.check_dt_s
            )
        except Exception:
            log.exception("first_violation raised; treating it as a violation now")
            return t_from

    def _branch_request(
        self,
        seq: int,
        T: float,
        goal: Goal,
        forecast: HumanForecast,
        active: _Active,
        tau: float,
        s: float,
    ) -> tuple[BackupRequest, float] | None:
        """The backup request of frame ``seq`` and its branch point (path time in ``active``)."""
        cfg = self.config
        D = cfg.deadline_s
        deadline = D
        if active.kind == "hold":
            deadline = cfg.start_deadline
            t_start = max(T + deadline, self._not_before)
            tau_b = t_start  # a hold's path time runs with the clock
            q_s = active.traj.q(active.traj.t_end)
            qd_s = np.zeros(6)
        else:
            # fastest progress the ramp allows: the robot reaches the branch point at or after T + D
            # (a plan that ends before then: the robot rests at its end and the switch waits for T + D)
            tau_b = min(tau + _ramp_distance(s, cfg.scale_up_rate, D), active.traj.t_end)
            t_start = T + D
            q_s, qd_s = _state(active.traj, tau_b)
            if tau_b >= active.traj.t_end:
                qd_s = np.zeros(6)
        req = BackupRequest(
            key=seq,
            t_request=T,
            t_start=float(t_start),
            q_start=np.asarray(q_s, dtype=np.float64).reshape(6),
            qd_start=np.asarray(qd_s, dtype=np.float64).reshape(6),
            goal=goal,
            forecast=forecast,
            deadline_s=deadline,
        )
        return req, float(tau_b)

    def _schedule(
        self, req: BackupRequest, tau_b: float, active: _Active, reason: SwitchReason, t_v: float | None
    ) -> None:
        self.jobs.submit(req)
        self._pending = _Pending(
            key=req.key,
            t_switch=req.t_start,
            tau_branch=tau_b,
            plan_id=active.plan_id,
            reason=reason,
            violation_t=t_v,
            request=req,
        )

    def _backup_passes(
        self, pend: _Pending, out: PlanOutcome, t_now: float, tau: float, s: float, forecast: HumanForecast
    ) -> float | None:
        """Re-check a backup against ``forecast`` as it would run from the switch; returns the violation time
        that forbids the switch, or None when it may be executed: a violation after ``t_now + D`` is left to
        the next frames' backups, except on a plan that starts the robot moving (``clear_start``)."""
        assert out.traj is not None
        cfg = self.config
        tau_new = out.traj.t_start + max(tau - pend.tau_branch, 0.0)
        t_ref = max(t_now, pend.t_switch) if tau < pend.tau_branch else t_now
        view = ScaledView(out.traj, t_ref=t_ref, tau_ref=tau_new, scale=max(s, cfg.check_min_scale))
        t_v = self._first_violation(view, forecast, t_ref, view.t_end)
        if t_v is None:
            return None
        if t_v > t_now + cfg.deadline_s and not (cfg.clear_start and pend.from_rest):
            return None
        return t_v

    # ------------------------------------------------------------------------------------------------
    # stops and emergency plans
    # ------------------------------------------------------------------------------------------------

    def _stop_and_replan(self, t: float, *, reason: str, violation_t: float | None) -> None:
        """Brake along the path now; the emergency plan takes over at rest. Caller holds the lock."""
        cfg = self.config
        active = self._active
        s0 = self._s
        vmax = float(active.profile.window_at(self._tau).max())
        jmax = active.profile.joint_window_at(self._tau)
        rate = math.inf
        if vmax > 1e-9:
            rate = min(rate, cfg.brake_decel_mps2 / vmax)
        if jmax > 1e-9:
            rate = min(rate, cfg.brake_joint_decel / jmax)
        if not math.isfinite(rate) or s0 <= 0:
            rate = max(s0, 1e-3) / 1e-3
        t_b = s0 / rate
        self._brake = _Brake(
            t0=t,
            tau0=self._tau,
            s0=s0,
            rate=rate,
            t_stop=t + t_b,
            tau_stop=self._tau + 0.5 * s0 * t_b,
            reason=reason,
        )
        self._pending = None
        self._generation += 1
        self.counters.stop_replans += 1
        self._stopped_latch = True
        self._moved_since_stop = 0.0
        self._emit(t, "stop_replan", {"violation_t": violation_t, "reason": reason})
        self._set_state("collision_avoidance", t)

    def _plan_emergency(self, brake: _Brake, frame: HumanFrame, *, gen_after: int) -> None:
        """Compute the emergency plan from the stop point (the person held at ``frame``), and check it
        against the latest forecast. Runs outside the lock; attaches the result if the brake still stands."""
        cfg = self.config
        with self._lock:
            if self._brake is not brake:
                return
            active = self._active
            q_stop = np.asarray(active.traj.q(min(brake.tau_stop, active.traj.t_end)), dtype=np.float64)
            brake.emergency_tried = True
        held = HumanForecast.hold(frame, margin_m=cfg.tracking_margin_m)
        c0 = self.timer()
        em: _Active | None = None
        try:
            res = self.planner.emergency(
                q_start=q_stop.reshape(6),
                t_start=brake.t_stop,
                forecast=held,
                horizon_s=cfg.emergency_horizon,
            )
            if res.ok and res.plan is not None:
                traj = self.make_trajectory(res.plan, np.zeros(6))
                prof = SpeedProfile.of(traj, self.geometry, window_s=cfg.profile_window_s)
                em = _Active(traj, prof, self._new_plan_id(), "emergency", False, self._goal, -1)
            else:
                reason = str(res.reason)
        except Exception as exc:
            log.exception("emergency plan raised")
            reason = f"{type(exc).__name__}: {exc}"
        compute_s = self.timer() - c0
        fixed = getattr(self.jobs, "fixed_compute_s", None)
        if fixed is not None:  # compute times fixed (deterministic headless runs): a tenth of a backup's
            compute_s = 0.1 * float(fixed)
        with self._lock:
            self.counters.emergency_plans += 1
            if em is None:
                self.counters.plan_failures += 1
                self._emit(brake.t0, "plan_failed", {"reason": f"emergency: {reason}"})
            if self._brake is brake:
                brake.emergency = em
                brake.emergency_ready_t = brake.t0 + compute_s

    # ------------------------------------------------------------------------------------------------
    # servo tick
    # ------------------------------------------------------------------------------------------------

    def servo(self, t: float) -> ServoCommand:
        """Advance execution to time ``t`` (s) and return the command for the robot."""
        with self._lock:
            dt = max(float(t) - self._t, 0.0)
            self._t = float(t)
            if self._estop or self._fault:
                self._s = 0.0
                self._v_cmd[:] = 0.0
                self._v_inst[:] = 0.0
                self._account(dt)
                return ServoCommand(t, self._q_cmd.copy(), np.zeros(6), 0.0, True)
            if self._brake is not None:
                self._servo_brake(t)
            else:
                self._servo_governed(t, dt)
            active = self._active
            tau = min(self._tau, active.traj.t_end) if active.kind != "hold" else active.traj.t_end
            q, qd = _state(active.traj, tau)
            qd = qd * self._s
            if not active.under_way(self._tau):
                qd = np.zeros(6)
            self._travel_m += self._v_cmd * dt
            self._q_cmd = q
            self._account(dt)
            return ServoCommand(t, q.copy(), qd, self._s, bool(not np.any(qd)))

    def _servo_brake(self, t: float) -> None:
        b = self._brake
        assert b is not None
        if t < b.t_stop:
            u = t - b.t0
            self._s = max(b.s0 - b.rate * u, 0.0)
            self._tau = b.tau0 + b.s0 * u - 0.5 * b.rate * u * u
            self._v_cmd = self._s * self._active.profile.window_at(self._tau)
            self._v_inst = self._s * self._active.profile.speed_at(self._tau)
            return
        self._s = 0.0
        self._v_cmd[:] = 0.0
        self._v_inst[:] = 0.0
        self._tau = b.tau_stop
        if self._state != "stopped" and t >= b.t_stop:
            self._set_state("stopped", b.t_stop)
        if not b.emergency_tried:
            return  # the frame thread is still computing it
        if t < b.emergency_ready_t:
            return
        self._brake = None
        self._generation += 1
        q_stop = np.asarray(self._active.traj.q(min(b.tau_stop, self._active.traj.t_end))).reshape(6)
        em = b.emergency
        if em is not None and self._forecast is not None:
            view = ScaledView(em.traj, t_ref=t, tau_ref=em.traj.t_start, scale=1.0)
            t_v = self._first_violation(view, self._forecast, t, view.t_end)
            if t_v is None:
                em.checked_seq = self._seq
                self._active = em
                self._tau = em.traj.t_start
                self._set_state("collision_avoidance", t)
                return
        self._activate_hold(q_stop, t)
        self._set_state("stopped", t)

    def _servo_governed(self, t: float, dt: float) -> None:
        cfg = self.config
        active = self._active
        pend = self._pending
        if active.kind == "hold":
            self._tau = t
        if (
            pend is not None
            and pend.plan_id == active.plan_id
            and t >= pend.t_switch - 1e-9
            and self._tau >= pend.tau_branch - 1e-9
        ):
            self._switch(pend, t)  # then govern the plan in execution now, in this same tick
            if self._brake is not None:
                self._servo_brake(t)
                return
            active = self._active
            pend = self._pending
        if active.kind == "hold":
            self._tau = t
            self._s = 0.0
            self._v_cmd[:] = 0.0
            self._v_inst[:] = 0.0
            return
        vmax = active.profile.window_at(self._tau)  # (L,)
        vtop = float(vmax.max())
        jmax = active.profile.joint_window_at(self._tau)
        # braking: the path scale falls at `rate` (1/s), each part slows at rate * its speed
        rate = math.inf
        if vtop > 1e-9:
            rate = cfg.brake_decel_mps2 / vtop
        if jmax > 1e-9:
            rate = min(rate, cfg.brake_joint_decel / jmax)
        s = self._s
        if self._stale:
            s_target = 0.0
        elif vtop <= 1e-9:
            s_target = 1.0
        else:
            # the scales this tick can reach: up at the ramp rate, down at the brake rate (any at rest)
            at_rest = float(self._v_inst.max()) <= 1e-6
            lo = 0.0 if at_rest or not math.isfinite(rate) else s - rate * dt
            s_target = self._governed_scale(t, dt, s, vmax, rate, lo, s + cfg.scale_up_rate * dt)
        if s_target >= s:
            s_new = min(s_target, s + cfg.scale_up_rate * dt)
        elif float(self._v_inst.max()) <= 1e-6:
            s_new = s = s_target  # at rest: lowering the scale brakes nothing
        else:
            s_new = max(s_target, s - rate * dt) if math.isfinite(rate) else s_target
        self._tau += 0.5 * (s + s_new) * dt
        self._s = s_new
        self._v_cmd = max(s, s_new) * vmax
        self._v_inst = s_new * active.profile.speed_at(self._tau)
        self._moved_since_stop += float(self._v_cmd.max()) * dt
        if self._moved_since_stop > self.config.resume_travel_m:
            self._stopped_latch = False
        if (
            pend is not None
            and pend.plan_id == active.plan_id
            and self._tau > pend.tau_branch
            and t + dt < pend.t_switch - 1e-9
        ):
            self._tau = pend.tau_branch  # never run past a branch point before its switch time
        if self._tau >= active.traj.t_end:
            self._tau = active.traj.t_end
            if active.complete and (pend is None or pend.plan_id != active.plan_id):
                self._arrive(t)

    def _switch(self, pend: _Pending, t: float) -> None:
        """The pending switch is due: take the backup, re-check it against the latest forecast, execute it
        or take the emergency path. Caller holds the lock."""
        self._pending = None
        out = pend.outcome if pend.outcome is not None else self.jobs.take(pend.key, pend.request)
        self._record_plan(out, t)
        active = self._active
        moving = active.kind != "hold" and active.complete
        if out.status != "ok" and pend.from_rest:
            self._retry_after = t + self.config.retry_after_s
        if out.status != "ok":
            if out.status == "deadline_miss":
                self.counters.deadline_misses += 1
                limit = pend.request.deadline_s if pend.request is not None else None
                payload = {"elapsed_s": out.compute_s, "deadline_s": limit or self.config.deadline_s}
                self._emit(t, "deadline_miss", payload)
            else:
                self.counters.plan_failures += 1
                self._emit(t, "plan_failed", {"reason": f"backup {out.status}: {out.reason}"})
            # a missed deadline or a planner fault takes the emergency path; a search that found no path
            # leaves the plan in execution (its violation is still ahead) to the next frames' backups
            if moving and pend.reason == "online_replan" and out.status in ("deadline_miss", "error"):
                self._emergency_path(t, reason=f"backup_{out.status}", violation_t=pend.violation_t)
            return
        if pend.checked_seq != self._seq and self._forecast is not None:
            t_v = self._backup_passes(pend, out, t, self._tau, self._s, self._forecast)
            if t_v is not None:
                self._emit(t, "plan_failed", {"reason": f"backup violates the latest forecast at {t_v:.3f}"})
                self.counters.plan_failures += 1
                if self.config.clear_start and pend.from_rest:
                    self._retry_after = t + self.config.retry_after_s
                if moving and pend.reason == "online_replan":
                    self._emergency_path(t, reason="backup_invalid", violation_t=t_v)
                return
        assert out.traj is not None and out.profile is not None
        tau_new = out.traj.t_start + max(self._tau - pend.tau_branch, 0.0)
        pid = self._new_plan_id()
        self._active = _Active(out.traj, out.profile, pid, "plan", True, self._goal, self._seq)
        self._tau = tau_new
        self._generation += 1
        if pend.reason == "online_replan":
            self.counters.online_replans += 1
            self._emit(t, "online_replan", {"t_switch": t, "violation_t": pend.violation_t})
        self._set_state("nominal", t)

    def _emergency_path(self, t: float, *, reason: str, violation_t: float | None) -> None:
        """Stop and switch to the emergency plan (planned inline: the servo tick does this rarely)."""
        self._stop_and_replan(t, reason=reason, violation_t=violation_t)
        brake = self._brake
        frame = self._frame
        if brake is not None and frame is not None:
            self._plan_emergency(brake, frame, gen_after=self._generation)
        elif brake is not None:
            brake.emergency_tried = True
            brake.emergency_ready_t = t

    def _record_plan(self, out: PlanOutcome, t: float) -> None:
        if out.status == "skipped":
            return
        self.counters.plans_computed += 1
        self.counters.planning_times_s.append(out.compute_s)

    def _arrive(self, t: float) -> None:
        active = self._active
        q_goal = np.asarray(active.traj.q(active.traj.t_end)).reshape(6)
        self._arrived = active.goal
        self._goal = None
        self._pending = None
        self._activate_hold(q_goal, t)
        self._set_state("nominal", t)

    # ------------------------------------------------------------------------------------------------
    # helpers
    # ------------------------------------------------------------------------------------------------

    def _new_plan_id(self) -> int:
        self._plan_ids += 1
        return self._plan_ids

    def _hold(self, q: np.ndarray, t: float) -> _Active:
        traj = HoldTrajectory(q, t)
        prof = SpeedProfile.still(t, self.n_parts)
        return _Active(traj, prof, self._new_plan_id(), "hold", False, None, -1)

    def _activate_hold(self, q: np.ndarray, t: float) -> None:
        self._active = self._hold(q, t)
        self._tau = t
        self._s = 0.0
        self._generation += 1

    def _set_state(self, state: SupervisorState, t: float) -> None:
        if state != self._state:
            prev = self._state
            self._state = state
            self._emit(t, "state_changed", {"from": prev, "to": state})

    def _effective_state(self) -> SupervisorState:
        if self._fault:
            return "fault"
        if self._estop:
            return "estop"
        if self._stale:
            return "stopped"
        return self._state

    def _account(self, dt: float) -> None:
        st = self._effective_state()
        if st == "nominal" and self._active.kind != "hold" and self._s <= 1e-3 and self._goal is not None:
            st = "stopped"  # held at zero speed by the governor
        c = self.counters
        c.state_time_s[st] += dt
        if self._s > 1e-3 and self._active.under_way(self._tau):
            c.moving_time_s += dt
            c.scale_time_s += self._s * dt

    def _emit(self, t: float, kind: str, payload: dict[str, Any]) -> None:
        if self.on_event is not None:
            self.on_event(t, kind, payload)

    def begin(self, t: float) -> None:
        """Start supervising (a trial begins): state ``nominal``, robot held where it is."""
        with self._lock:
            self._t = t
            self._activate_hold(self._q_cmd, t)
            self._set_state("nominal", t)

    def end(self, t: float) -> None:
        """Stop supervising: drop plans, hold."""
        with self._lock:
            self._pending = None
            self._brake = None
            self._goal = None
            self._activate_hold(self._q_cmd, t)
            self._set_state("idle", t)

    def status(self) -> SupervisorStatus:
        """An immutable read-out (for snapshots)."""
        with self._lock:
            active = self._active
            pend = self._pending
            backup = pend.outcome.traj if pend is not None and pend.outcome is not None else None
            i = int(np.argmin(self._sep_m))
            v_h = self._v_h_bound(self._t)
            return SupervisorStatus(
                t=self._t,
                state=self._effective_state(),
                scale=self._s,
                separation_m=float(self._sep_m[i]),
                required_separation_m=float(
                    self.ssm.sp(float(self._v_cmd[i]), float(self._v_cmd.max()), float(v_h[i]))
                ),
                q=self._q_cmd.copy(),
                plan=None if active.kind == "hold" else active.traj,
                plan_tau=self._tau,
                backup=backup,
                stale=self._stale,
                estopped=self._estop,
            )

    def _older_frame(self, t: float) -> HumanFrame | None:
        """The newest remembered frame at or before ``t``."""
        for f in reversed(self._history):
            if f.t <= t + 1e-9:
                return f
        return None

    def _v_h_bound(self, t: float) -> np.ndarray:
        if not math.isfinite(self._v_h_t):
            return np.full(self.n_parts, self.ssm.human_speed_max_mps)
        _, v = self.ssm.human_approach(self._v_h0, t - self._v_h_t)
        return np.asarray(v)

    def _governed_scale(
        self, t: float, dt: float, s: float, vmax: np.ndarray, rate: float, lo: float, hi: float
    ) -> float:
        """The governor's target scale for the tick from ``t`` to ``t + dt`` (compiled:
        :func:`app.safety._kernels.governed_scale`; :meth:`_governed_scale_reference` in NumPy). Caller
        holds the lock."""
        law = self.speed_scale_law
        dt_h = t + dt - self._v_h_t if math.isfinite(self._v_h_t) else math.nan
        return float(
            _kernel_governed_scale(
                self._sep_m,
                self._x_h0,
                self._v_h0,
                self._travel_m,
                vmax,
                dt_h,
                s,
                dt,
                rate,
                lo,
                hi,
                _SCALES,
                _ENV_U,
                self.ssm._kernel_params,
                _NO_LAW if law is None else law.kernel_params,
            )
        )

    def _governed_scale_reference(
        self, t: float, dt: float, s: float, vmax: np.ndarray, rate: float, lo: float, hi: float
    ) -> float:
        """:meth:`_governed_scale` in NumPy. Caller holds the lock."""
        # separation lower bound of each part at the next tick
        sep_lb, v_h = self._separation_bound(t + dt)
        sep_lb = sep_lb - s * vmax * dt
        m = vmax > 1e-4
        s_target = self.ssm.max_scale_reference(
            sep_lb[m], v_human_mps=v_h[m], v_parts_mps=vmax[m], rate=rate, lo=lo, hi=hi
        )
        if self.speed_scale_law is not None and np.any(m):
            # the standard's law with the person's measured speed (the envelope above already covers
            # their worst-case speed-up since it was measured, with the stopping time of this speed)
            law = self.speed_scale_law(sep_lb[m], vmax[m], np.maximum(self._v_h0[m], 0.0))
            s_target = min(s_target, max(law, 0.0))
        return s_target

    def _separation_bound(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Per robot part: a lower bound of the separation at time ``t`` (m) and an upper bound of the
        person's approach speed then (m/s), from the last measurement, the person's worst case since, and
        the part's travel. Caller holds the lock."""
        if not math.isfinite(self._v_h_t):
            return self._sep_m.copy(), np.full(self.n_parts, self.ssm.human_speed_max_mps)
        x1, v1 = self.ssm.human_approach(self._v_h0, t - self._v_h_t)
        return self._sep_m - (x1 - self._x_h0) - self._travel_m, np.asarray(v1)

    def recent_decide_s(self) -> tuple[float, ...]:
        with self._lock:
            return tuple(self._recent_decide_s)


def _state(traj: TrajectoryLike, t: float) -> tuple[np.ndarray, np.ndarray]:
    """``(q(t), qd(t))`` (6,) each, through the trajectory's one-look-up ``state`` where it has one."""
    state = getattr(traj, "state", None)
    if state is not None:
        q, qd = state(t)
    else:
        q, qd = traj.q(t), traj.qd(t)
    return np.asarray(q, dtype=np.float64).reshape(6), np.asarray(qd, dtype=np.float64).reshape(6)


def _ramp_distance(s: float, up_rate: float, horizon_s: float) -> float:
    """Path-time distance covered in ``horizon_s`` starting at scale ``s`` and ramping up at ``up_rate``
    to 1 (the fastest the robot can progress)."""
    if s >= 1.0:
        return horizon_s
    t_full = (1.0 - s) / up_rate if up_rate > 0 else math.inf
    if t_full >= horizon_s:
        return s * horizon_s + 0.5 * up_rate * horizon_s**2
    return s * t_full + 0.5 * up_rate * t_full**2 + (horizon_s - t_full)
