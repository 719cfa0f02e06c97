"""Time-variant A* over the static roadmap (sequential and batched-parallel), emergency plans, validity check.

Paper, section II-A, and where this goes further:

- **State.** Per roadmap node ``v`` the search keeps the arrival time ``AT(v)`` and the configuration
  ``Cfg(v)`` (one IK branch), in arrays the search owns; states are immutable records (node, time,
  configuration, path speed, parent record, departure time), so a plan is always rebuilt from exactly the
  configurations and times that were checked. The roadmap is never written to.
- **Expansion u -> v.** The IK branches of ``v`` (each shifted by multiples of 2 pi next to ``Cfg(u)``) are
  ordered by the time a straight joint move needs; the first one that passes is taken (at most
  ``max_branch_tries``). A move between the same branch at both ends uses the roadmap's static edge check;
  any other move (another branch, the start connection) is checked against the static scene on the fly.
- **Edge timing.** The paper lets every edge last as long as the slowest joint needs at its velocity limit.
  With the UR5e's acceleration limits that is too optimistic near starts and stops, and a trajectory fitted to
  it would run late: the forecast person would then be checked at the wrong time. Here the path speed (the
  largest joint speed as a fraction of its limit) follows a 1-D profile: it accelerates with the smallest
  joint acceleration/velocity ratio up to ``speed_fraction`` and brakes to rest on the edge into the goal (and
  before a wait). The heuristic stays admissible: the straight-line joint-space time at the cruise speed.
- **Validity against the forecast.** A move is valid if at every sampled instant (every ``sample_dt_s`` and
  at its end) the surface distance robot-person is at least :func:`app.planning.safety.robot_clearance` for
  the move's robot speed (``S_r + S_s + C + Z_d + Z_r``) plus the forecast's margin at that instant (it grows
  with the horizon; beyond the horizon the last pose is held and the margin grows at ``growth_mps``) plus
  ``corridor_margin_m`` (room for the fitted spline's deviation from the straight moves). The forecast takes
  the place of ISO/TS 15066's worst-case ``S_h = v_h (T_r + T_s)`` over the planning horizon; the supervisor
  applies the full ``S_p`` to the current pose on top (speed scaling), so both views hold at run time.
- **Waiting (safe-interval style).** When every branch of a move is blocked, the search may wait at ``u``
  in steps of ``wait_step_s`` up to ``max_wait_s`` (if standing still there is itself safe) and try again.
  Without a person the search is plain A*.
- **Parallel.** ``workers = N`` pops up to N states per step and evaluates all their successors, branches,
  waits and time samples in one vectorised distance call (the batched equivalent of the paper's N threads
  taking nodes from the open list in turn; in CPython threads would serialise on the interpreter lock).
  States are immutable records and ``AT`` is updated only when an arrival improves it, so the validity
  guarantees are the same as sequentially; a node may be re-expanded when a later batch improves it.
- **Trajectory check.** The waypoints become a C1 spline (:class:`app.planning.trajectory.Trajectory`),
  possibly retimed to the acceleration limits; it is verified against the forecast at ``verify_dt_s``
  with :meth:`Planner.first_violation` (and against the static scene). If it fails, the search is repeated
  once with a time-robust check (each robot sample against the person over ``[t, t + slack]``); if that fails
  too, the result is a failure. A returned plan carries the verified knots (``Plan.qd``).
- **Emergency plan.** The person is held at the current pose; the robot stays put if that is safe for the
  horizon, else the search stops as soon as a state reaches ``t_start + horizon_s`` (paper: ``F + D``).
"""

from __future__ import annotations

import heapq
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from app.planning.roadmap import NUM_BRANCHES, Roadmap
from app.planning.safety import SSMParams, robot_clearance
from app.planning.trajectory import Plan, Trajectory, TrajectoryError, fit_knots

if TYPE_CHECKING:
    from app.prediction.forecast import HumanForecast

logger = logging.getLogger(__name__)

_TWO_PI = 2.0 * math.pi
_EPS_T = 1e-9


class RobotModel(Protocol):
    """What the planner needs from the collision model (:class:`app.planning.collision.CollisionModel`)."""

    def distance_to_human_paired(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray: ...

    def in_static_collision(self, q: np.ndarray, *, margin_m: float = 0.0) -> np.ndarray: ...

    def self_collision(self, q: np.ndarray) -> np.ndarray: ...

    def robot_capsules(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@dataclass(frozen=True, slots=True)
class PlannerConfig:
    """Settings of the time-variant search (see the module docstring for the policy they configure).

    Attributes:
        ssm: ISO/TS 15066 parameters (``S_r``, ``S_s``, ``C``, ``Z_d``, ``Z_r`` are required around the
            forecast person; ``S_h`` is replaced by the forecast).
        speed_fraction: Cruise path speed as a fraction of the joint velocity limits (the largest joint moves
            at ``speed_fraction * QD_MAX``).
        accel_fraction: Fraction of the joint acceleration limits the edge timing plans with (the rest is
            room for the spline fit at corners).
        min_edge_s: Shortest duration of a move (s).
        sample_dt_s: Largest time step between checked instants of a move (s); its end is always checked.
        corridor_margin_m: Extra clearance (m) that absorbs the spline's deviation from the straight moves.
        speed_factor: Robot speed for ``S_r + S_s`` = chord speed of the arm's points x this factor (>= 1:
            the spline's peak speed on a segment exceeds its average, and arcs are longer than chords).
        wait_step_s, max_wait_s: Waiting at a node: step and longest wait (s); ``max_wait_s = 0`` disables it.
        max_branch_tries: How many IK branches of a successor are tried (nearest first).
        goal_hold_s: After arriving at the goal the robot must be able to stand there this long (s).
        start_neighbors: Number of roadmap nodes the start configuration is connected to.
        check_step_rad: Largest joint step (rad) between configurations checked against the static scene.
        static_margin_m: Clearance (m) from the static scene for on-the-fly checks (as the roadmap's).
        max_expansions: Bound on expanded states per search.
        verify_dt_s: Time step (s) of the fitted trajectory's verification.
        fallback_slack_s: Extra time window (s) of the time-robust re-search after a failed verification.
        emergency_hold_s: An emergency plan's final configuration must be safe this long (s).
        q_min, q_max, qd_max, qdd_max: Joint limits (6,) (rad, rad/s, rad/s^2); None: the UR5e's.
    """

    ssm: SSMParams = field(default_factory=SSMParams)
    speed_fraction: float = 0.5
    accel_fraction: float = 0.8
    min_edge_s: float = 0.02
    sample_dt_s: float = 0.05
    corridor_margin_m: float = 0.02
    speed_factor: float = 1.3
    wait_step_s: float = 0.1
    max_wait_s: float = 1.0
    max_branch_tries: int = 3
    goal_hold_s: float = 0.3
    start_neighbors: int = 8
    check_step_rad: float = 0.05
    static_margin_m: float = 0.0
    max_expansions: int = 20000
    verify_dt_s: float = 0.01
    fallback_slack_s: float = 0.3
    emergency_hold_s: float = 0.3
    q_min: tuple[float, ...] | None = None
    q_max: tuple[float, ...] | None = None
    qd_max: tuple[float, ...] | None = None
    qdd_max: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.speed_fraction must be in (0, 1], got {self.speed_fraction}")
        if not 0.0 < self.accel_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.accel_fraction must be in (0, 1], got {self.accel_fraction}")
        for name in ("sample_dt_s", "verify_dt_s", "check_step_rad", "wait_step_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.max_branch_tries < 1 or self.start_neighbors < 1:
            raise ValueError("PlannerConfig.max_branch_tries and start_neighbors must be >= 1")
        if self.speed_factor < 1.0:
            raise ValueError(f"PlannerConfig.speed_factor must be >= 1, got {self.speed_factor}")


@dataclass(frozen=True, slots=True)
class PlanResult:
    """The outcome of a planning query.

    Attributes:
        ok: Whether a verified plan was found.
        plan: The plan (knots of the verified trajectory, ``plan.qd`` set) or None.
        reason: ``"ok"`` / ``"stay"`` (emergency: standing still is safe) or why it failed.
        expanded: States expanded by the search(es).
        compute_s: Wall time of the query (s).
        trajectory: The verified trajectory (the same as ``Trajectory.from_plan(plan)``) or None.
    """

    ok: bool
    plan: Plan | None
    reason: str
    expanded: int
    compute_s: float
    trajectory: Trajectory | None = None


class _States:
    """Immutable state records of one search, in growable arrays (owned by the search, never the roadmap)."""

    __slots__ = ("branch", "dep", "n", "node", "parent", "pts", "q", "t", "u")

    def __init__(self, capacity: int, n_pts: int) -> None:
        self.n = 0
        self.node = np.empty(capacity, dtype=np.int64)
        self.branch = np.empty(capacity, dtype=np.int64)
        self.t = np.empty(capacity)
        self.u = np.empty(capacity)
        self.q = np.empty((capacity, 6))
        self.parent = np.empty(capacity, dtype=np.int64)
        self.dep = np.empty(capacity)
        self.pts = np.empty((capacity, n_pts, 3))

    def _grow(self, need: int) -> None:
        cap = self.node.shape[0]
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ("node", "branch", "t", "u", "q", "parent", "dep", "pts"):
            old = getattr(self, name)
            arr = np.empty((new, *old.shape[1:]), dtype=old.dtype)
            arr[: self.n] = old[: self.n]
            setattr(self, name, arr)

    def add(
        self,
        node: np.ndarray,
        branch: np.ndarray,
        t: np.ndarray,
        u: np.ndarray,
        q: np.ndarray,
        parent: np.ndarray,
        dep: np.ndarray,
        pts: np.ndarray,
    ) -> np.ndarray:
        k = node.shape[0]
        self._grow(self.n + k)
        sl = slice(self.n, self.n + k)
        self.node[sl], self.branch[sl], self.t[sl], self.u[sl] = node, branch, t, u
        self.q[sl], self.parent[sl], self.dep[sl], self.pts[sl] = q, parent, dep, pts
        ids = np.arange(self.n, self.n + k)
        self.n += k
        return ids


def _profile(
    u0: np.ndarray, L: np.ndarray, f: float, A: float, end_rest: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D path-speed profile of a move: duration, exit speed and peak speed.

    Path position is the max-norm joint distance in "seconds at full joint speed" (``L``); speeds are
    fractions of full speed, ``A`` is the path acceleration (1/s). The move starts at ``u0``, accelerates at
    ``A`` toward the cruise speed ``f`` and, if ``end_rest``, brakes at ``A`` to stop at the end (a move that
    cannot stop in time brakes uniformly; the spline fit retimes it and the verification has the last word).
    """
    u0 = np.minimum(u0, f)
    with np.errstate(divide="ignore", invalid="ignore"):
        d_acc = (f * f - u0 * u0) / (2 * A)
        reach = d_acc >= L
        u1s = np.sqrt(u0 * u0 + 2 * A * L)
        t_free = np.where(reach, (u1s - u0) / A, (f - u0) / A + (L - d_acc) / f)
        u_free = np.where(reach, u1s, f)
        up = np.minimum(f, np.sqrt((2 * A * L + u0 * u0) / 2))
        can_stop = u0 * u0 / (2 * A) <= L
        d1 = (up * up - u0 * u0) / (2 * A)
        d3 = up * up / (2 * A)
        t_rest = (up - u0) / A + np.maximum(L - d1 - d3, 0.0) / np.maximum(up, 1e-12) + up / A
        t_forced = 2 * L / np.maximum(u0, 1e-12)
        t_rest = np.where(can_stop, t_rest, t_forced)
    dur = np.where(end_rest, t_rest, t_free)
    u_end = np.where(end_rest, 0.0, u_free)
    peak = np.where(end_rest, np.where(can_stop, up, u0), u_free)
    zero = L <= 1e-12
    dur = np.where(zero, 0.0, dur)
    u_end = np.where(zero, np.where(end_rest, 0.0, u0), u_end)
    peak = np.where(zero, u0, peak)
    return dur, u_end, peak


def _profile_fraction(
    tau: np.ndarray, u0: np.ndarray, L: np.ndarray, h: np.ndarray, f: float, A: float, end_rest: np.ndarray
) -> np.ndarray:
    """Fraction (0..1) of a move's path covered ``tau`` seconds after its start (same model as _profile).

    ``h`` is the move's actual duration (it may be longer than the profile's when clamped to ``min_edge_s``;
    the profile is then stretched uniformly).
    """
    dur, _, _ = _profile(u0, L, f, A, end_rest)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(h > 0, dur / h, 1.0)
        s = tau * scale  # time in the profile's own clock
        u0c = np.minimum(u0, f)
        # not ending at rest: accelerate, then cruise
        t1 = np.maximum((f - u0c) / A, 0.0)
        d_acc = u0c * t1 + 0.5 * A * t1 * t1
        pos_free = np.where(s <= t1, u0c * s + 0.5 * A * s * s, d_acc + f * (s - t1))
        # ending at rest: accelerate to up, cruise, brake
        up = np.minimum(f, np.sqrt((2 * A * L + u0c * u0c) / 2))
        can_stop = u0c * u0c / (2 * A) <= L
        ta = np.maximum((up - u0c) / A, 0.0)
        da = u0c * ta + 0.5 * A * ta * ta
        tb = up / A
        rem = dur - s
        pos_rest = np.where(
            s <= ta,
            u0c * s + 0.5 * A * s * s,
            np.where(rem <= tb, L - 0.5 * A * rem * rem, da + up * (s - ta)),
        )
        a_forced = u0c / np.maximum(dur, 1e-12)
        pos_forced = u0c * s - 0.5 * a_forced * s * s
        pos_rest = np.where(can_stop, pos_rest, pos_forced)
        pos = np.where(end_rest, pos_rest, pos_free)
        frac = np.where(L > 1e-12, pos / L, 1.0)
    return np.clip(frac, 0.0, 1.0)


class _Checker:
    """Checks robot samples (configuration, time, speed) against a forecast (or nothing)."""

    def __init__(
        self,
        model: RobotModel,
        forecast: HumanForecast | None,
        ssm: SSMParams,
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
    ) -> None:
        self.model = model
        self.forecast = forecast
        self.ssm = ssm
        self.extra_m = extra_m
        self.offsets = offsets
        self.floor_m = floor_m
        self.samples = 0

    def __call__(self, q: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Boolean (S,): sample k is safe (robot ``q[k]`` at time ``t[k]`` moving at ``v[k]`` m/s)."""
        S = q.shape[0]
        if self.forecast is None or S == 0:
            return np.ones(S, dtype=bool)
        n_off = len(self.offsets)
        if n_off == 1:
            tt = t + self.offsets[0]
            qq, vv = q, v
        else:
            tt = (t[None, :] + np.asarray(self.offsets)[:, None]).reshape(-1)
            qq = np.broadcast_to(q, (n_off, S, 6)).reshape(-1, 6)
            vv = np.broadcast_to(v, (n_off, S)).reshape(-1)
        joints, margins = self.forecast.poses_at(tt)
        d = self.model.distance_to_human_paired(qq, joints)
        req = robot_clearance(vv, self.ssm) + margins + self.extra_m
        if self.floor_m is not None:
            req = np.minimum(req, self.floor_m)
        ok = d >= req
        self.samples += qq.shape[0]
        if n_off > 1:
            ok = ok.reshape(n_off, S).all(axis=0)
        return ok


class Planner:
    """Time-variant A* over a roadmap, against a forecast of the person.

    Args:
        roadmap: The static roadmap (shared, never modified).
        collision: The collision model (:class:`app.planning.collision.CollisionModel`, or anything with
            the methods of :class:`RobotModel`).
        config: Search settings.
        timer: Monotonic clock for deadlines and ``compute_s`` (seconds); injectable for tests.

    Thread safety: every query keeps its state in its own arrays; one planner can serve concurrent queries.
    """

    def __init__(
        self,
        roadmap: Roadmap,
        collision: RobotModel,
        *,
        config: PlannerConfig | None = None,
        timer: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.roadmap = roadmap
        self.collision = collision
        self.config = config or PlannerConfig()
        self._timer = timer
        cfg = self.config
        if cfg.qd_max is None or cfg.qdd_max is None or cfg.q_min is None or cfg.q_max is None:
            from app.planning import kinematics

            d_qmin, d_qmax, d_qd, d_qdd = (
                kinematics.Q_MIN,
                kinematics.Q_MAX,
                kinematics.QD_MAX,
                kinematics.QDD_MAX,
            )
        else:
            d_qmin = d_qmax = d_qd = d_qdd = None
        self.q_min = np.asarray(cfg.q_min if cfg.q_min is not None else d_qmin, dtype=np.float64)
        self.q_max = np.asarray(cfg.q_max if cfg.q_max is not None else d_qmax, dtype=np.float64)
        self.qd_max = np.asarray(cfg.qd_max if cfg.qd_max is not None else d_qd, dtype=np.float64)
        self.qdd_max = np.asarray(cfg.qdd_max if cfg.qdd_max is not None else d_qdd, dtype=np.float64)
        for name in ("q_min", "q_max", "qd_max", "qdd_max"):
            if getattr(self, name).shape != (6,):
                raise ValueError(f"Planner: {name} must have shape (6,)")
        self._inv_qd = 1.0 / self.qd_max
        # path acceleration in "fraction of full speed per second"
        self._A = float(np.min(self.qdd_max / self.qd_max)) * cfg.accel_fraction
        # Robot points (capsule end points) per node and branch, for the chord speed of moves.
        N = roadmap.num_nodes
        q_all = roadmap.ik.reshape(-1, 6)
        self._pts_all = self._points(q_all).reshape(N, NUM_BRANCHES, -1, 3)
        self._n_pts = self._pts_all.shape[2]
        self._ik = roadmap.ik
        self._valid = roadmap.valid
        self._nbranch_valid = roadmap.valid.sum(axis=1)

    # ------------------------------------------------------------------------------------------ helpers
    def _points(self, q: np.ndarray) -> np.ndarray:
        """Points (B, P, 3) on the robot (capsule end points) whose speeds bound the robot's speed."""
        a, b, _ = self.collision.robot_capsules(np.asarray(q, dtype=np.float64).reshape(-1, 6))
        return np.concatenate([a, b], axis=1)

    def _align(self, q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
        """2 pi-shift every joint of ``q`` (..., 6) next to ``q_ref`` (broadcastable) within the limits."""
        nearest = q + _TWO_PI * np.rint((q_ref - q) * (1.0 / _TWO_PI))
        over = nearest > self.q_max
        under = nearest < self.q_min
        nearest = np.where(over, nearest - _TWO_PI, nearest)
        nearest = np.where(under, nearest + _TWO_PI, nearest)
        bad = (nearest > self.q_max) | (nearest < self.q_min)
        return np.where(bad, q, nearest)

    def _metric(self, dq: np.ndarray) -> np.ndarray:
        """Straight-move length (...,) in seconds at full joint speed: max_j |dq_j| / qd_max_j."""
        return np.max(np.abs(dq) * self._inv_qd, axis=-1)

    def _static_free(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """Whether the straight joint moves qa[k] -> qb[k] ((M, 6) each) are free of the static scene and
        of self-collision at every configuration at most ``check_step_rad`` apart (endpoints included)."""
        M = qa.shape[0]
        if M == 0:
            return np.ones(0, dtype=bool)
        step = self.config.check_step_rad
        n = np.maximum(np.ceil(np.max(np.abs(qb - qa), axis=1) / step).astype(np.int64), 1)
        idx = np.repeat(np.arange(M), n + 1)
        start = np.cumsum(n + 1) - (n + 1)
        i = np.arange(idx.shape[0]) - start[idx]
        frac = i / n[idx]
        q = qa[idx] + frac[:, None] * (qb - qa)[idx]
        bad = self.collision.in_static_collision(q, margin_m=self.config.static_margin_m) | (
            self.collision.self_collision(q)
        )
        bad |= ~self._within_limits(q)
        ok = np.ones(M, dtype=bool)
        np.logical_and.at(ok, idx, ~bad)
        return ok

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        return np.all((q >= self.q_min - 1e-9) & (q <= self.q_max + 1e-9), axis=-1)

    def _heuristic_fn(self, goal: int | None, f: float) -> Callable[[np.ndarray], np.ndarray]:
        if goal is None:
            return lambda q: np.zeros(q.shape[0])
        G = self._ik[goal][self._valid[goal]]  # (nb, 6)
        inv = self._inv_qd / f

        def h(q: np.ndarray) -> np.ndarray:
            d = q[:, None, :] - G[None, :, :]
            d = np.abs(d - _TWO_PI * np.rint(d * (1.0 / _TWO_PI)))
            return np.min(np.max(d * inv, axis=-1), axis=-1)

        return h

    # ------------------------------------------------------------------------------------------ public
    def plan(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        goal: str | int,
        forecast: HumanForecast | None,
        workers: int = 1,
        deadline_s: float | None = None,
        qd0: np.ndarray | None = None,
    ) -> PlanResult:
        """Plan from a configuration at a time to a station or node, safe against a forecast person.

        Args:
            q_start: Start configuration (6,) (rad); need not be a roadmap node.
            t_start: Start time (s, runtime clock, the same clock as the forecast's).
            goal: Station name (``home``, ``pickup``, ``A``..., ``A_approach``...) or roadmap node index.
            forecast: The person's forecast, or None for a static plan (no person).
            workers: States expanded per search step (1 = sequential A*; N > 1 = batched parallel A*).
            deadline_s: Compute-time budget (s); the query fails with reason ``"deadline"`` past it.
            qd0: Joint velocity (6,) at ``t_start`` (rad/s) of the motion being executed (default: at rest).

        Returns:
            A :class:`PlanResult`; ``ok`` only with a trajectory verified against ``forecast``.
        """
        t0 = self._timer()
        q_start = np.asarray(q_start, dtype=np.float64).reshape(-1)
        if q_start.shape != (6,) or not np.all(np.isfinite(q_start)):
            raise ValueError(f"q_start must be a finite (6,) configuration, got {q_start!r}")
        goal_node = self.roadmap.resolve(goal)
        deadline = None if deadline_s is None else t0 + deadline_s
        cfg = self.config
        expanded = 0
        if not self._valid[goal_node].any():
            return PlanResult(False, None, "goal node has no valid IK branch", 0, self._timer() - t0)
        start_check = _Checker(self.collision, forecast, cfg.ssm, extra_m=0.0)
        if not start_check(q_start[None], np.array([t_start]), np.zeros(1))[0]:
            return PlanResult(
                False, None, "start configuration violates the separation at t_start", 0, self._timer() - t0
            )
        attempts: list[tuple[float, ...]] = [(0.0,)]
        if forecast is not None and cfg.fallback_slack_s > 0:
            s = cfg.fallback_slack_s
            attempts.append((-0.25 * s, 0.0, 0.5 * s, s))
        reason = "no plan"
        for offsets in attempts:
            checker = _Checker(
                self.collision, forecast, cfg.ssm, extra_m=cfg.corridor_margin_m, offsets=offsets
            )
            waypoints, n_exp, reason = self._search(
                q_start=q_start,
                t_start=t_start,
                goal=goal_node,
                stop_time=None,
                checker=checker,
                workers=workers,
                deadline=deadline,
                hold_s=cfg.goal_hold_s,
            )
            expanded += n_exp
            if waypoints is None:
                break  # the time-robust check cannot succeed where the plain one failed
            result = self._finish(waypoints, qd0, forecast, hold_s=cfg.goal_hold_s)
            if result is not None:
                plan, traj = result
                return PlanResult(True, plan, "ok", expanded, self._timer() - t0, traj)
            reason = "trajectory failed verification against the forecast"
            if deadline is not None and self._timer() > deadline:
                reason = "deadline"
                break
        return PlanResult(False, None, reason, expanded, self._timer() - t0)

    def emergency(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        forecast: HumanForecast,
        horizon_s: float,
        qd0: np.ndarray | None = None,
        workers: int = 4,
    ) -> PlanResult:
        """A short safe motion with the person held still at their pose at ``t_start``.

        Stands still when that is safe for ``horizon_s`` (+ ``emergency_hold_s``); otherwise searches until
        a state reaches ``t_start + horizon_s`` (paper: ``F + D``). When the robot already violates the
        separation at ``t_start``, moves are accepted that never come closer to the person than it is now.

        Args:
            q_start: Current configuration (6,). t_start: now (s). forecast: the latest forecast (its pose at
            ``t_start`` is held, with its margin there and its growth rate). horizon_s: ``F + D`` (s).
            qd0: Current joint velocity (6,) (rad/s); the trajectory brakes from it.
            workers: States expanded per search step.
        """
        from app.prediction.forecast import HumanForecast

        t0 = self._timer()
        cfg = self.config
        q_start = np.asarray(q_start, dtype=np.float64).reshape(6)
        joints, margin = forecast.pose_at(t_start)
        held = HumanForecast(
            t0=t_start,
            times=np.array([t_start]),
            joints=joints[None],
            margins=np.array([margin]),
            growth_mps=forecast.growth_mps,
            max_margin_m=forecast.max_margin_m,
        )
        hold_s = max(cfg.emergency_hold_s, 0.0)
        t_stop = t_start + max(horizon_s, 0.0)
        # 1. Standing still (braking from qd0) when that is safe.
        stay = Plan(times=np.array([t_start]), q=q_start[None], nodes=np.array([-1]))
        traj = self._fit(stay, qd0)
        if traj is not None and self._verify(traj, held, t_start, max(t_stop, traj.t_end) + hold_s) is None:
            plan = traj.to_plan()
            return PlanResult(True, plan, "stay", 0, self._timer() - t0, traj)
        # 2. Moving: search until t_stop; escape mode if the start already violates.
        d0 = float(self.collision.distance_to_human_paired(q_start[None], joints[None])[0])
        req0 = float(robot_clearance(0.0, cfg.ssm)) + margin
        floor = d0 - 1e-3 if d0 < req0 else None
        checker = _Checker(self.collision, held, cfg.ssm, extra_m=cfg.corridor_margin_m, floor_m=floor)
        waypoints, expanded, reason = self._search(
            q_start=q_start,
            t_start=t_start,
            goal=None,
            stop_time=t_stop,
            checker=checker,
            workers=workers,
            deadline=None,
            hold_s=hold_s,
        )
        if waypoints is not None:
            result = self._finish(waypoints, qd0, held, hold_s=hold_s, floor_m=floor)
            if result is not None:
                plan, traj = result
                return PlanResult(True, plan, "ok", expanded, self._timer() - t0, traj)
            reason = "trajectory failed verification"
        return PlanResult(False, None, reason, expanded, self._timer() - t0)

    def first_violation(
        self,
        traj: Trajectory,
        forecast: HumanForecast | None,
        *,
        t_from: float,
        t_to: float,
        dt_s: float | None = None,
    ) -> float | None:
        """The earliest time in ``[t_from, t_to]`` at which ``traj`` breaks the required separation.

        The requirement at time t: surface distance robot-person >= ``S_r + S_s + C + Z_d + Z_r`` for the
        robot's speed at t (the largest speed of any capsule end point) + the forecast's margin at t; also a
        configuration outside the joint limits counts as a violation. Sampled every ``dt_s`` (default
        ``verify_dt_s``), both ends included. Returns None when there is no violation.
        """
        return self._verify(traj, forecast, t_from, t_to, dt_s=dt_s, static=False)

    # ------------------------------------------------------------------------------------------ internals
    def _fit(self, plan: Plan, qd0: np.ndarray | None) -> Trajectory | None:
        try:
            times, q, qd = fit_knots(plan.times, plan.q, qd0=qd0, qd_max=self.qd_max, qdd_max=self.qdd_max)
        except TrajectoryError as exc:
            logger.debug("trajectory fit failed: %s", exc)
            return None
        return Trajectory(times, q, qd)

    def _verify(
        self,
        traj: Trajectory,
        forecast: HumanForecast | None,
        t_from: float,
        t_to: float,
        *,
        dt_s: float | None = None,
        static: bool = True,
        floor_m: float | None = None,
    ) -> float | None:
        dt = self.config.verify_dt_s if dt_s is None else dt_s
        ts = traj.sample(dt, t_from=t_from, t_to=max(t_to, t_from))
        q = traj.q(ts)
        bad = ~self._within_limits(q)
        if static:
            moving = (ts >= traj.t_start) & (ts <= traj.t_end)
            if np.any(moving):
                qm = q[moving]
                sb = self.collision.in_static_collision(
                    qm, margin_m=self.config.static_margin_m
                ) | self.collision.self_collision(qm)
                bad[np.flatnonzero(moving)[sb]] = True
        if forecast is not None:
            eps = 1e-4
            p0 = self._points(q)
            p1 = self._points(traj.q(ts + eps))
            v = np.max(np.linalg.norm(p1 - p0, axis=-1), axis=-1) / eps
            joints, margins = forecast.poses_at(ts)
            d = self.collision.distance_to_human_paired(q, joints)
            req = robot_clearance(v, self.config.ssm) + margins
            if floor_m is not None:
                req = np.minimum(req, floor_m)
            bad |= d < req
        if not np.any(bad):
            return None
        return float(ts[np.argmax(bad)])

    def _finish(
        self,
        waypoints: Plan,
        qd0: np.ndarray | None,
        forecast: HumanForecast | None,
        *,
        hold_s: float,
        floor_m: float | None = None,
    ) -> tuple[Plan, Trajectory] | None:
        traj = self._fit(waypoints, qd0)
        if traj is None:
            return None
        viol = self._verify(traj, forecast, traj.t_start, traj.t_end + hold_s, floor_m=floor_m)
        if viol is not None:
            logger.debug(
                "fitted trajectory violates at t=%.3f (plan %.3f..%.3f)", viol, traj.t_start, traj.t_end
            )
            return None
        nodes = _map_nodes(waypoints, traj)
        return traj.to_plan(nodes), traj

    def _start_candidates(self, q_start: np.ndarray) -> np.ndarray:
        """The ``start_neighbors`` nodes nearest the start (by their nearest branch), nearest first."""
        aligned = self._align(self._ik, q_start[None, None, :])
        L = np.where(self._valid, self._metric(aligned - q_start), np.inf)
        best = L.min(axis=1)
        k = min(self.config.start_neighbors, int(np.isfinite(best).sum()))
        if k == 0:
            return np.zeros(0, dtype=np.int64)
        nodes = np.argpartition(best, k - 1)[:k]
        return nodes[np.argsort(best[nodes])]

    def _search(
        self,
        *,
        q_start: np.ndarray,
        t_start: float,
        goal: int | None,
        stop_time: float | None,
        checker: _Checker,
        workers: int,
        deadline: float | None,
        hold_s: float,
    ) -> tuple[Plan | None, int, str]:
        """The time-variant A*. Returns (waypoints or None, expanded states, reason)."""
        cfg = self.config
        rm = self.roadmap
        N = rm.num_nodes
        f = cfg.speed_fraction
        A = self._A
        workers = max(int(workers), 1)
        heur = self._heuristic_fn(goal, f)
        states = _States(256, self._n_pts)
        AT = np.full(N, np.inf)
        start_pts = self._points(q_start[None])
        sid0 = states.add(
            np.array([-1]),
            np.array([-1]),
            np.array([t_start]),
            np.array([0.0]),
            q_start[None],
            np.array([-1]),
            np.array([t_start]),
            start_pts,
        )[0]
        heap: list[tuple[float, float, int]] = [
            (t_start + float(heur(q_start[None])[0]), -t_start, int(sid0))
        ]
        expanded = 0
        wait_safe_until: dict[int, float] = {}
        while heap:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            seen: set[int] = set()
            while heap and len(batch) < workers:
                _, _, sid = heapq.heappop(heap)
                node = int(states.node[sid])
                if node >= 0 and (states.t[sid] > AT[node] + _EPS_T or node in seen):
                    continue  # superseded by a better arrival
                if (goal is not None and node == goal) or (
                    stop_time is not None and states.t[sid] >= stop_time
                ):
                    return self._reconstruct(states, sid), expanded, "ok"
                seen.add(node)
                batch.append(sid)
            if not batch:
                break
            expanded += len(batch)
            new = self._expand(
                states, np.array(batch), AT, checker, goal, stop_time, hold_s, wait_safe_until, f, A
            )
            if new.size:
                hv = heur(states.q[new])
                tv = states.t[new]
                if stop_time is not None:
                    hv = np.maximum(stop_time - tv, 0.0)
                for sid, fv, tt in zip(new.tolist(), (tv + hv).tolist(), tv.tolist(), strict=True):
                    heapq.heappush(heap, (fv, -tt, sid))
        what = "goal" if goal is not None else "the emergency horizon"
        return None, expanded, f"{what} unreachable: no safe path found after {expanded} expansions"

    def _expand(
        self,
        states: _States,
        batch: np.ndarray,
        AT: np.ndarray,
        checker: _Checker,
        goal: int | None,
        stop_time: float | None,
        hold_s: float,
        wait_safe_until: dict[int, float],
        f: float,
        A: float,
    ) -> np.ndarray:
        """Expand a batch of states; returns the ids of the new states."""
        cfg = self.config
        rm = self.roadmap
        # ---- candidate moves (parent, successor node, edge mask; the start's moves are checked on the fly)
        par_l, node_l, mask_l = [], [], []
        for sid in batch.tolist():
            u = int(states.node[sid])
            if u < 0:
                nodes = self._start_candidates(states.q[sid])
                par_l.append(np.full(nodes.shape[0], sid))
                node_l.append(nodes)
                mask_l.append(np.zeros(nodes.shape[0], dtype=np.int64))
            else:
                a, b = rm.indptr[u], rm.indptr[u + 1]
                par_l.append(np.full(b - a, sid))
                node_l.append(rm.indices[a:b])
                mask_l.append(rm.edge_branches[a:b].astype(np.int64))
        par = np.concatenate(par_l)
        cv = np.concatenate(node_l)
        emask = np.concatenate(mask_l)
        M = cv.shape[0]
        if M == 0:
            return np.zeros(0, dtype=np.int64)
        q_par = states.q[par]
        t_par = states.t[par]
        u_par = states.u[par]
        br_par = states.branch[par]
        aligned = self._align(self._ik[cv], q_par[:, None, :])  # (M, 8, 6)
        dq = aligned - q_par[:, None, :]
        L = np.where(self._valid[cv], self._metric(dq), np.inf)  # (M, 8)
        order = np.argsort(L, axis=1, kind="stable")  # branches nearest first
        R = min(cfg.max_branch_tries, NUM_BRANCHES)
        order = order[:, :R]
        # static status from the roadmap: same branch as the parent, the edge's bit set, the same (short) move
        rows = np.arange(M)[:, None]
        br = order
        L_r = L[rows, br]
        same = (br == br_par[:, None]) & ((emask[:, None] >> br) & 1).astype(bool)
        if np.any(same):
            ref = self._ik[states.node[par].clip(0)][rows, br]  # parent's stored branch rep
            ref_target = self._align(self._ik[cv][rows, br], ref)
            same &= np.all(np.abs((ref_target - ref) - dq[rows, br]) < 1e-6, axis=-1)
        end_rest = np.zeros(M, dtype=bool) if goal is None else (cv == goal)
        u0 = np.broadcast_to(u_par[:, None], L_r.shape)
        h, u_end, peak = _profile(u0, np.where(np.isfinite(L_r), L_r, 0.0), f, A, end_rest[:, None])
        h = np.where(L_r > 1e-12, np.maximum(h, cfg.min_edge_s), 0.0)
        arrival = t_par[:, None] + h
        alive = np.isfinite(L_r) & (arrival < AT[cv][:, None] - _EPS_T)
        resolved = ~alive.any(axis=1)
        static_ok = np.where(same, 1, 0)  # 1 ok, 0 unknown, -1 blocked
        new_ids: list[np.ndarray] = []
        chosen_par, chosen_v, chosen_b, chosen_t, chosen_u, chosen_dep = [], [], [], [], [], []

        def accept(
            idx: np.ndarray, r: np.ndarray, dep: np.ndarray, t_arr: np.ndarray, u_arr: np.ndarray
        ) -> None:
            chosen_par.append(par[idx])
            chosen_v.append(cv[idx])
            chosen_b.append(br[idx, r])
            chosen_t.append(t_arr)
            chosen_u.append(u_arr)
            chosen_dep.append(dep)

        # ---- rounds over branch ranks, departing at once
        for r in range(R):
            idx = np.flatnonzero(~resolved & alive[:, r])
            if idx.size == 0:
                continue
            unknown = idx[static_ok[idx, r] == 0]
            if unknown.size:
                okk = self._static_free(q_par[unknown], aligned[unknown, br[unknown, r]])
                static_ok[unknown, r] = np.where(okk, 1, -1)
            idx = idx[static_ok[idx, r] == 1]
            if idx.size == 0:
                continue
            ok = self._check_moves(
                states,
                par[idx],
                cv[idx],
                br[idx, r],
                aligned[idx, br[idx, r]],
                t_par[idx],
                h[idx, r],
                u0[idx, r],
                L_r[idx, r],
                end_rest[idx],
                peak[idx, r],
                checker,
                goal,
                hold_s,
            )
            good = idx[ok]
            if good.size:
                accept(good, np.full(good.size, r), t_par[good], arrival[good, r], u_end[good, r])
                resolved[good] = True
        # ---- waits: every unresolved candidate whose parent can stand still
        pending = np.flatnonzero(~resolved)
        if pending.size and cfg.max_wait_s > 0 and checker.forecast is not None:
            self._try_waits(
                states,
                pending,
                par,
                cv,
                br,
                aligned,
                static_ok,
                L_r,
                end_rest,
                AT,
                checker,
                goal,
                hold_s,
                wait_safe_until,
                f,
                A,
                accept,
            )
        if not chosen_par:
            return np.zeros(0, dtype=np.int64)
        c_par = np.concatenate(chosen_par)
        c_v = np.concatenate(chosen_v)
        c_b = np.concatenate(chosen_b)
        c_t = np.concatenate(chosen_t)
        c_u = np.concatenate(chosen_u)
        c_dep = np.concatenate(chosen_dep)
        # relax: keep the earliest arrival per node, only where it improves AT
        o = np.lexsort((c_t, c_v))
        c_par, c_v, c_b, c_t, c_u, c_dep = c_par[o], c_v[o], c_b[o], c_t[o], c_u[o], c_dep[o]
        first = np.ones(c_v.shape[0], dtype=bool)
        first[1:] = c_v[1:] != c_v[:-1]
        keep = first & (c_t < AT[c_v] - _EPS_T)
        if not np.any(keep):
            return np.zeros(0, dtype=np.int64)
        c_par, c_v, c_b, c_t, c_u, c_dep = (x[keep] for x in (c_par, c_v, c_b, c_t, c_u, c_dep))
        AT[c_v] = c_t
        q_new = self._align(self._ik[c_v, c_b], states.q[c_par])
        ids = states.add(c_v, c_b, c_t, c_u, q_new, c_par, c_dep, self._pts_all[c_v, c_b])
        new_ids.append(ids)
        return np.concatenate(new_ids)

    def _move_samples(
        self,
        q_a: np.ndarray,
        q_b: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        v_mps: np.ndarray,
        hold_mask: np.ndarray,
        hold_s: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Sample moves (M of them) in time; returns (owner (S,), q (S, 6), t (S,), v (S,))."""
        cfg = self.config
        M = q_a.shape[0]
        n = np.maximum(np.ceil(h / cfg.sample_dt_s - 1e-9).astype(np.int64), 1)
        n_hold = np.where(hold_mask, max(math.ceil(hold_s / cfg.sample_dt_s - 1e-9), 0), 0)
        tot = n + n_hold
        owner = np.repeat(np.arange(M), tot)
        start = np.cumsum(tot) - tot
        i = np.arange(owner.shape[0]) - start[owner] + 1  # 1..tot
        in_move = i <= n[owner]
        tau = np.where(in_move, i / n[owner] * h[owner], h[owner])
        frac = _profile_fraction(
            tau, u0[owner], L[owner], h[owner], self.config.speed_fraction, self._A, end_rest[owner]
        )
        frac = np.where(in_move, frac, 1.0)
        q = q_a[owner] + frac[:, None] * (q_b - q_a)[owner]
        t_hold = np.where(in_move, 0.0, (i - n[owner]) * (hold_s / np.maximum(n_hold[owner], 1)))
        t = t_dep[owner] + tau + t_hold
        v = np.where(in_move, v_mps[owner], 0.0)
        return owner, q, t, v

    def _move_speed(
        self, pts_a: np.ndarray, pts_b: np.ndarray, h: np.ndarray, L: np.ndarray, peak: np.ndarray
    ) -> np.ndarray:
        """Robot speed (m/s) used for ``S_r + S_s`` on each move: the largest chord speed of the arm's
        points, scaled from the move's average path speed to its peak, times ``speed_factor``."""
        chord = np.max(np.linalg.norm(pts_b - pts_a, axis=-1), axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            avg = np.where(h > 0, L / h, 0.0)
            ratio = np.where(avg > 1e-12, np.maximum(peak / avg, 1.0), 1.0)
            v = np.where(h > 0, chord / h * ratio, 0.0)
        return v * self.config.speed_factor

    def _check_moves(
        self,
        states: _States,
        par: np.ndarray,
        cv: np.ndarray,
        br: np.ndarray,
        q_b: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        peak: np.ndarray,
        checker: _Checker,
        goal: int | None,
        hold_s: float,
    ) -> np.ndarray:
        """Check moves against the forecast (plus the hold at the goal); boolean (M,)."""
        M = par.shape[0]
        if checker.forecast is None:
            return np.ones(M, dtype=bool)
        v = self._move_speed(states.pts[par], self._pts_all[cv, br], h, L, peak)
        hold_mask = (cv == goal) if goal is not None else np.zeros(M, dtype=bool)
        if goal is None and hold_s > 0:
            hold_mask = np.ones(M, dtype=bool)  # emergency: any end point may become the final one
        owner, q, t, vv = self._move_samples(
            states.q[par], q_b, t_dep, h, u0, L, end_rest, v, hold_mask, hold_s
        )
        ok_s = checker(q, t, vv)
        ok = np.ones(M, dtype=bool)
        np.logical_and.at(ok, owner, ok_s)
        return ok

    def _try_waits(
        self,
        states: _States,
        pending: np.ndarray,
        par: np.ndarray,
        cv: np.ndarray,
        br: np.ndarray,
        aligned: np.ndarray,
        static_ok: np.ndarray,
        L_r: np.ndarray,
        end_rest: np.ndarray,
        AT: np.ndarray,
        checker: _Checker,
        goal: int | None,
        hold_s: float,
        wait_safe_until: dict[int, float],
        f: float,
        A: float,
        accept: Callable[..., None],
    ) -> None:
        """Waiting at the parent, then moving: all (candidate, branch, wait step) combinations at once."""
        cfg = self.config
        K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
        if K < 1:
            return
        # how long each parent can stand still
        parents = np.unique(par[pending])
        todo = [int(p) for p in parents.tolist() if int(p) not in wait_safe_until]
        if todo:
            sub = max(1, math.ceil(cfg.wait_step_s / cfg.sample_dt_s - 1e-9))
            n = K * sub
            dt = cfg.wait_step_s / sub
            tp = np.array(todo)
            ts = states.t[tp][:, None] + dt * np.arange(1, n + 1)[None, :]
            qs = np.repeat(states.q[tp], n, axis=0)
            ok = checker(qs, ts.reshape(-1), np.zeros(tp.size * n)).reshape(tp.size, n)
            for j, p in enumerate(todo):
                bad = np.flatnonzero(~ok[j])
                wait_safe_until[p] = float(ts[j, bad[0]]) if bad.size else math.inf
        R = br.shape[1]
        ks = np.arange(1, K + 1)
        # combinations (candidate, rank, k)
        cand = np.repeat(pending, R * K)
        rank = np.tile(np.repeat(np.arange(R), K), pending.size)
        kk = np.tile(ks, pending.size * R)
        t_wait_end = states.t[par[cand]] + kk * cfg.wait_step_s
        safe_until = np.array([wait_safe_until[int(p)] for p in par[cand].tolist()])
        Lc = L_r[cand, rank]
        u0 = np.zeros(cand.shape[0])
        h, u_end, peak = _profile(u0, np.where(np.isfinite(Lc), Lc, 0.0), f, A, end_rest[cand])
        h = np.where(Lc > 1e-12, np.maximum(h, cfg.min_edge_s), 0.0)
        arrival = t_wait_end + h
        live = (
            np.isfinite(Lc)
            & (static_ok[cand, rank] == 1)
            & (t_wait_end < safe_until - _EPS_T)
            & (arrival < AT[cv[cand]] - _EPS_T)
        )
        if not np.any(live):
            return
        sel = np.flatnonzero(live)
        c, r, k = cand[sel], rank[sel], kk[sel]
        ok = self._check_moves(
            states,
            par[c],
            cv[c],
            br[c, r],
            aligned[c, br[c, r]],
            t_wait_end[sel],
            h[sel],
            u0[sel],
            Lc[sel],
            end_rest[c],
            peak[sel],
            checker,
            goal,
            hold_s,
        )
        if not np.any(ok):
            return
        c, r, k, sel = c[ok], r[ok], k[ok], sel[ok]
        # per candidate the shortest wait, then the nearest branch
        o = np.lexsort((r, k, c))
        c, r, k, sel = c[o], r[o], k[o], sel[o]
        first = np.ones(c.shape[0], dtype=bool)
        first[1:] = c[1:] != c[:-1]
        c, r, sel = c[first], r[first], sel[first]
        accept(c, r, t_wait_end[sel], arrival[sel], u_end[sel])

    def _reconstruct(self, states: _States, sid: int) -> Plan:
        chain = []
        s = sid
        while s >= 0:
            chain.append(s)
            s = int(states.parent[s])
        chain.reverse()
        times, qs, nodes = [], [], []
        for i, s in enumerate(chain):
            if i > 0:
                p = chain[i - 1]
                if states.dep[s] > states.t[p] + _EPS_T:  # waited at the parent
                    times.append(float(states.dep[s]))
                    qs.append(states.q[p])
                    nodes.append(int(states.node[p]))
            times.append(float(states.t[s]))
            qs.append(states.q[s])
            nodes.append(int(states.node[s]))
        return Plan(times=np.array(times), q=np.array(qs), nodes=np.array(nodes))


def _map_nodes(waypoints: Plan, traj: Trajectory) -> np.ndarray:
    """Roadmap node of each trajectory knot (matched in order by configuration; -1 for added knots)."""
    kq = traj.knot_q
    out = np.full(kq.shape[0], -1, dtype=np.int64)
    j = 0
    for i in range(kq.shape[0]):
        for jj in range(j, waypoints.q.shape[0]):
            if np.allclose(waypoints.q[jj], kq[i], atol=1e-9):
                out[i] = waypoints.nodes[jj]
                j = jj
                break
    return out


__all__ = ["Plan", "PlanResult", "Planner", "PlannerConfig", "RobotModel"]
