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
  at its end) the surface distance robot-person is at least :func:`app.planning.safety.forecast_clearance`
  for the move's robot speed and the forecast's margin at that instant (``S_r + S_s + C + Z_r +
  max(Z_d, margin)``; the margin grows with the horizon; beyond the horizon the last pose is held and the
  margin grows at ``growth_mps`` up to a cap) plus ``corridor_margin_m`` (room for the fitted spline's
  deviation from the straight moves). The forecast takes
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
from app.planning.safety import SSMParams, forecast_clearance
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

    def human_capsules(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


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
        wait_step_s, max_wait_s: Waiting at a node (nearest branch only): step and longest wait (s);
            ``max_wait_s = 0`` disables it.
        max_branch_tries: How many IK branches of a successor are tried (nearest first).
        slow_speed_fractions: When every branch is blocked at the cruise speed, the nearest one is tried
            again at these lower cruise speeds (a slower robot needs less ``S_r + S_s``) before waiting.
        goal_hold_s: After arriving at the goal the robot must be able to stand there this long (s).
        start_neighbors: Number of roadmap nodes the start configuration is connected to.
        check_step_rad: Largest joint step (rad) between configurations checked against the static scene.
        static_margin_m: Clearance (m) from the static scene for on-the-fly checks (as the roadmap's).
        max_expansions: Bound on expanded states per search.
        verify_dt_s: Time step (s) of the fitted trajectory's verification.
        fallback_slack_s: Extra time window (s) of the time-robust re-search after a failed verification.
        emergency_hold_s: An emergency plan's final configuration must be safe this long (s).
        lever_arm_m: Upper bound (m) on the distance of any point of the robot from any joint axis: a
            joint move by ``dq`` moves no point further than ``sum(|dq|) * lever_arm_m`` (used by the
            broad phase that skips exact distance checks far from the person; 1.3 m covers the UR5e with
            a 0.15 m tool).
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
    max_wait_s: float = 0.6
    max_branch_tries: int = 2
    slow_speed_fractions: tuple[float, ...] = (0.2,)
    goal_hold_s: float = 0.3
    start_neighbors: int = 8
    check_step_rad: float = 0.05
    static_margin_m: float = 0.0
    max_expansions: int = 20000
    verify_dt_s: float = 0.01
    fallback_slack_s: float = 0.3
    emergency_hold_s: float = 0.3
    lever_arm_m: float = 1.3
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

    __slots__ = ("branch", "cen", "dep", "n", "node", "parent", "pts", "q", "rad", "t", "u")

    _FIELDS = ("node", "branch", "t", "u", "q", "parent", "dep", "pts", "cen", "rad")

    def __init__(self, capacity: int, n_pts: int, n_caps: int) -> None:
        self.n = 0
        self.node = np.empty(capacity, dtype=np.int64)
        self.branch = np.empty(capacity, dtype=np.int64)
        self.t = np.empty(capacity)
        self.u = np.empty(capacity)
        self.q = np.empty((capacity, 6))
        self.parent = np.empty(capacity, dtype=np.int64)
        self.dep = np.empty(capacity)
        self.pts = np.empty((capacity, n_pts, 3))
        self.cen = np.empty((capacity, n_caps, 3))
        self.rad = np.empty((capacity, n_caps))

    def add(self, **cols: np.ndarray) -> np.ndarray:
        k = cols["node"].shape[0]
        cap = self.node.shape[0]
        if self.n + k > cap:
            new = max(self.n + k, 2 * cap)
            for name in self._FIELDS:
                old = getattr(self, name)
                arr = np.empty((new, *old.shape[1:]), dtype=old.dtype)
                arr[: self.n] = old[: self.n]
                setattr(self, name, arr)
        sl = slice(self.n, self.n + k)
        for name in self._FIELDS:
            getattr(self, name)[sl] = cols[name]
        ids = np.arange(self.n, self.n + k)
        self.n += k
        return ids


def _profile(
    u0: np.ndarray, L: np.ndarray, f: float, A: float, end_rest: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D path-speed profile of moves: duration, exit speed and peak speed (arrays shaped like ``L``).

    Path position is the max-norm joint distance in "seconds at full joint speed" (``L``); speeds are
    fractions of full speed, ``A`` is the path acceleration (1/s). A move starts at ``u0``, accelerates at
    ``A`` toward the cruise speed ``f`` and, where ``end_rest``, brakes at ``A`` to stop at its end (a move
    that cannot stop in time brakes uniformly; the spline fit retimes it and the verification has the last
    word).
    """
    L = np.asarray(L, dtype=np.float64)
    u0 = np.minimum(np.broadcast_to(u0, L.shape), f)
    u0sq = u0 * u0
    u1 = np.minimum(np.sqrt(u0sq + 2.0 * A * L), f)
    dur = (u1 - u0) / A + np.maximum(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f
    u_end = u1.copy()
    peak = u1.copy()
    er = np.broadcast_to(end_rest, L.shape)
    if er.any():
        idx = np.nonzero(er)
        ue, Le = u0[idx], L[idx]
        up = np.minimum(f, np.sqrt((2.0 * A * Le + ue * ue) / 2.0))
        can = ue * ue <= 2.0 * A * Le
        cruise = np.maximum(Le - (up * up - ue * ue) / (2.0 * A) - up * up / (2.0 * A), 0.0)
        t_rest = (up - ue) / A + cruise / np.maximum(up, 1e-12) + up / A
        dur[idx] = np.where(can, t_rest, 2.0 * Le / np.maximum(ue, 1e-12))
        u_end[idx] = 0.0
        peak[idx] = np.where(can, up, ue)
    return dur, u_end, peak


def _profile_fraction(
    tau: np.ndarray, u0: np.ndarray, L: np.ndarray, h: np.ndarray, f: float, A: float, end_rest: np.ndarray
) -> np.ndarray:
    """Fraction (0..1) of a move's path covered ``tau`` seconds after its start (the model of _profile).

    ``h`` is the move's actual duration (longer than the profile's when clamped to ``min_edge_s``: the
    profile is then stretched uniformly). All arguments are arrays of the same shape (one entry per sample).
    """
    dur, _, _ = _profile(u0, L, f, A, end_rest)
    s = tau * np.where(h > 0, dur / np.maximum(h, 1e-12), 1.0)  # time on the profile's own clock
    u0c = np.minimum(u0, f)
    t1 = (f - u0c) / A
    pos = np.where(s <= t1, (u0c + 0.5 * A * s) * s, (u0c + 0.5 * A * t1) * t1 + f * (s - t1))
    if end_rest.any():
        idx = np.flatnonzero(end_rest)
        ue, Le, se, de = u0c[idx], L[idx], s[idx], dur[idx]
        up = np.minimum(f, np.sqrt((2.0 * A * Le + ue * ue) / 2.0))
        can = ue * ue <= 2.0 * A * Le
        ta = (up - ue) / A
        rem = de - se
        p_rest = np.where(
            se <= ta,
            (ue + 0.5 * A * se) * se,
            np.where(rem <= up / A, Le - 0.5 * A * rem * rem, (ue + 0.5 * A * ta) * ta + up * (se - ta)),
        )
        a_forced = ue / np.maximum(de, 1e-12)
        pos[idx] = np.where(can, p_rest, ue * se - 0.5 * a_forced * se * se)
    return np.clip(np.where(L > 1e-12, pos / np.maximum(L, 1e-12), 1.0), 0.0, 1.0)


def _person_parts(model: RobotModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body parts for the broad phase: joint groups whose bounding boxes contain whole person capsules.

    Returns ``(part_of_joint (P, J) bool, caps_flat (C,), caps_start (P + 1,))``: which joints bound each
    part, and for part p the person capsules ``caps_flat[caps_start[p]:caps_start[p + 1]]`` it contains.
    Parts: torso with head, shoulders and hips; each arm; each leg (every capsule has both ends in one).
    """
    from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS

    groups = (
        ("pelvis", "spine", "chest", "neck", "head", "l_shoulder", "r_shoulder", "l_hip", "r_hip"),
        ("l_shoulder", "l_elbow", "l_wrist", "l_hand"),
        ("r_shoulder", "r_elbow", "r_wrist", "r_hand"),
        ("l_hip", "l_knee", "l_ankle"),
        ("r_hip", "r_knee", "r_ankle"),
    )
    member = np.zeros((len(groups), NUM_JOINTS), dtype=bool)
    for p, g in enumerate(groups):
        member[p, [JOINT_INDEX[n] for n in g]] = True
    # which joints each person capsule runs between: feed joint indices as coordinates
    coded = np.repeat(np.arange(NUM_JOINTS, dtype=np.float64)[None, :, None], 3, axis=2)
    ha, hb, _ = model.human_capsules(coded)
    ja, jb = ha[0, :, 0].astype(np.int64), hb[0, :, 0].astype(np.int64)
    caps: list[list[int]] = [[] for _ in groups]
    for m, (x, y) in enumerate(zip(ja.tolist(), jb.tolist(), strict=True)):
        p = next((p for p in range(len(groups)) if member[p, x] and member[p, y]), None)
        if p is None:
            raise ValueError(f"person capsule {m} (joints {x}-{y}) is not inside one body part")
        caps[p].append(m)
    start = np.cumsum([0] + [len(c) for c in caps])
    return member, np.array([m for c in caps for m in c], dtype=np.int64), start


class _Separation:
    """Pass/fail of robot samples against a forecast person.

    Two stages, both conservative: (1) a bounding sphere per robot capsule (known without forward
    kinematics from the move's end configurations, see :meth:`Planner._moves_ok`) against a box per body
    part; (2) for the (sample, robot capsule, part) triples still close, the exact distance between the robot
    capsule and each person capsule of the part (:func:`app.planning.collision.segment_distance`).
    """

    def __init__(
        self,
        model: RobotModel,
        forecast: HumanForecast | None,
        ssm: SSMParams,
        parts: tuple[np.ndarray, np.ndarray, np.ndarray],
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
    ) -> None:
        self.model = model
        self.forecast = forecast
        self.ssm = ssm
        self.member, self.caps_flat, self.caps_start = parts
        self.extra_m = extra_m
        self.offsets = offsets
        self.floor_m = floor_m
        self.samples = 0
        self.exact_pairs = 0
        self._human_r: np.ndarray | None = None

    def check(
        self,
        q: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        cen: np.ndarray | None = None,
        rad: np.ndarray | None = None,
    ) -> np.ndarray:
        """Boolean (S,): robot ``q[k]`` (6,) at time ``t[k]`` moving at ``v[k]`` m/s keeps the separation.

        ``cen`` (S, L, 3) / ``rad`` (S, L): spheres that contain the robot capsules at each sample, if known.
        """
        S = q.shape[0]
        if self.forecast is None or S == 0:
            return np.ones(S, dtype=bool)
        n_off = len(self.offsets)
        if n_off > 1:
            t = (t[None, :] + np.asarray(self.offsets)[:, None]).reshape(-1)
            q = np.broadcast_to(q, (n_off, S, 6)).reshape(-1, 6)
            v = np.broadcast_to(v, (n_off, S)).reshape(-1)
            if cen is not None and rad is not None:
                cen = np.broadcast_to(cen, (n_off, *cen.shape)).reshape(-1, *cen.shape[1:])
                rad = np.broadcast_to(rad, (n_off, *rad.shape)).reshape(-1, rad.shape[1])
        elif self.offsets[0] != 0.0:
            t = t + self.offsets[0]
        joints, margins = self.forecast.poses_at(t)
        req = forecast_clearance(v, margins, self.ssm) + self.extra_m
        if self.floor_m is not None:
            req = np.minimum(req, self.floor_m)
        n = q.shape[0]
        self.samples += n
        if self._human_r is None:
            self._human_r = np.asarray(self.model.human_capsules(joints[:1])[2], dtype=np.float64)
        hr = self._human_r
        P = self.member.shape[0]
        if cen is not None and rad is not None:
            L = cen.shape[1]
            close = np.empty((n, L, P), dtype=bool)
            for p in range(P):
                pj = joints[:, self.member[p]]
                r_p = float(hr[self.caps_flat[self.caps_start[p] : self.caps_start[p + 1]]].max(initial=0.0))
                plo = pj.min(axis=1)[:, None, :] - r_p
                phi = pj.max(axis=1)[:, None, :] + r_p
                g = np.maximum(np.maximum(plo - cen, cen - phi), 0.0)
                close[:, :, p] = np.sqrt(np.einsum("slk,slk->sl", g, g)) - rad < req[:, None]
            si, li, pi = np.nonzero(close)
        else:
            L = -1
            si = li = pi = None
        ok = np.ones(n, dtype=bool)
        if si is not None and si.size == 0:
            return ok.reshape(n_off, S).all(axis=0) if n_off > 1 else ok
        from app.planning.collision import segment_distance

        us, inv = np.unique(np.arange(n) if si is None else si, return_inverse=True)
        ra, rb, rr = self.model.robot_capsules(q[us])
        ha, hb, _ = self.model.human_capsules(joints[us])
        if si is None:  # every (capsule, person capsule) pair
            L, M = ra.shape[1], ha.shape[1]
            k = np.repeat(np.arange(us.size), L * M)
            lk = np.tile(np.repeat(np.arange(L), M), us.size)
            mk = np.tile(np.arange(M), us.size * L)
        else:
            cnt = np.diff(self.caps_start)[pi]
            k = np.repeat(inv, cnt)
            lk = np.repeat(li, cnt)
            first = np.repeat(self.caps_start[pi] - (np.cumsum(cnt) - cnt), cnt)
            mk = self.caps_flat[first + np.arange(int(cnt.sum()))]
        # bounding spheres of the exact robot capsules and of the person capsules first
        rc = 0.5 * (ra + rb)
        rrho = 0.5 * np.linalg.norm(rb - ra, axis=-1) + rr
        hc = 0.5 * (ha + hb)
        hrho = 0.5 * np.linalg.norm(hb - ha, axis=-1) + hr
        dc = rc[k, lk] - hc[k, mk]
        gap = np.sqrt(np.einsum("ij,ij->i", dc, dc)) - rrho[k, lk] - hrho[k, mk]
        near = np.flatnonzero(gap < req[us[k]])
        k, lk, mk = k[near], lk[near], mk[near]
        self.exact_pairs += k.size
        if k.size:
            d = segment_distance(ra[k, lk], rb[k, lk], ha[k, mk], hb[k, mk]) - rr[lk] - hr[mk]
            bad = d < req[us[k]]
            ok[us[k[bad]]] = False
        return ok.reshape(n_off, S).all(axis=0) if n_off > 1 else ok


@dataclass
class _Query:
    """Per-query context (the search's own state lives in :class:`_States` and ``AT``)."""

    sep: _Separation
    goal: int | None
    stop_time: float | None
    hold_s: float
    f: float
    A: float
    AT: np.ndarray
    states: _States
    h_tab: np.ndarray | None
    wait_safe_until: dict[int, float] = field(default_factory=dict)


class Planner:
    """Time-variant A* over a roadmap, against a forecast of the person.

    Args:
        roadmap: The static roadmap (shared, never modified).
        collision: The collision model (:class:`app.planning.collision.CollisionModel`, or anything with
            the methods of :class:`RobotModel`).
        config: Search settings.
        timer: Monotonic clock for deadlines and ``compute_s`` (seconds); injectable for tests.

    Construction precomputes, per roadmap edge and parent branch, the successor branches in order of joint
    distance (and per node and branch the robot's capsule points and bounding box); queries only read them.
    Every query keeps its state in its own arrays: one planner can serve concurrent queries.
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
        from app.planning import kinematics

        def pick(value: tuple[float, ...] | None, default: np.ndarray) -> np.ndarray:
            arr = np.asarray(default if value is None else value, dtype=np.float64)
            if arr.shape != (6,):
                raise ValueError(f"Planner: joint limits must have 6 entries, got {arr.shape}")
            return arr

        self.q_min = pick(cfg.q_min, kinematics.Q_MIN)
        self.q_max = pick(cfg.q_max, kinematics.Q_MAX)
        self.qd_max = pick(cfg.qd_max, kinematics.QD_MAX)
        self.qdd_max = pick(cfg.qdd_max, kinematics.QDD_MAX)
        self._inv_qd = 1.0 / self.qd_max
        # path acceleration in "fraction of full speed per second"
        self._A = float(np.min(self.qdd_max / self.qd_max)) * cfg.accel_fraction
        self._ik = roadmap.ik
        self._valid = roadmap.valid
        self._parts = _person_parts(collision)
        N = roadmap.num_nodes
        pts, cen, rad = self._points_and_spheres(roadmap.ik.reshape(-1, 6))
        self._pts_all = pts.reshape(N, NUM_BRANCHES, -1, 3)
        self._cen_all = cen.reshape(N, NUM_BRANCHES, -1, 3)
        self._rad_all = rad.reshape(N, NUM_BRANCHES, -1)
        self._n_pts = self._pts_all.shape[2]
        self._n_caps = self._cen_all.shape[2]
        self._lever, self._moved_by = self._lever_model()
        self._R = min(cfg.max_branch_tries, NUM_BRANCHES)
        self._build_edge_tables()
        self._static_boxes = self._static_box_bounds()
        self._h_cache: dict[int, np.ndarray] = {}
        self._static_memo: dict[tuple[int, int, int, int], int] = {}

    # ------------------------------------------------------------------------------------------ set-up
    def _points_and_spheres(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Capsule end points (B, 2L, 3) of configurations (B, 6), and a bounding sphere per capsule:
        centres (B, L, 3) and radii (B, L)."""
        a, b, r = self.collision.robot_capsules(np.asarray(q, dtype=np.float64).reshape(-1, 6))
        pts = np.concatenate([a, b], axis=1)
        return pts, 0.5 * (a + b), 0.5 * np.linalg.norm(b - a, axis=-1) + r

    def _lever_model(self) -> tuple[np.ndarray, np.ndarray]:
        """Per joint, a bound (6,) on any robot point's distance from its axis (m), and per capsule the last
        joint that moves it (L,) (1..6). For the UR5e capsule model both come from the geometry; for any other
        model every joint moves every capsule with ``lever_arm_m``."""
        from app.planning.collision import ROBOT_LINKS
        from app.planning.roadmap import _LINK_LAST_JOINT, lever_arms

        cell = getattr(self.collision, "cell", None)
        if cell is not None and self._n_caps == len(ROBOT_LINKS):
            return lever_arms(cell), np.array([_LINK_LAST_JOINT[n] for n in ROBOT_LINKS])
        return np.full(6, self.config.lever_arm_m), np.full(self._n_caps, 6)

    def _build_edge_tables(self) -> None:
        """Per CSR entry e = (u -> v) and parent branch b: v's branches nearest first (E, 8, R), the straight
        move lengths (E, 8, R) and whether the roadmap's static edge check covers the move (E, 8, R)."""
        rm = self.roadmap
        E = rm.indices.shape[0]
        R = self._R
        src = np.repeat(np.arange(rm.num_nodes), np.diff(rm.indptr))
        self._ord_tab = np.zeros((E, NUM_BRANCHES, R), dtype=np.int8)
        self._L_tab = np.full((E, NUM_BRANCHES, R), np.inf, dtype=np.float32)
        self._same_tab = np.zeros((E, NUM_BRANCHES, R), dtype=bool)
        bidx = np.arange(NUM_BRANCHES)
        for c0 in range(0, E, 2048):
            c1 = min(E, c0 + 2048)
            u, v = src[c0:c1], rm.indices[c0:c1]
            qu = self._ik[u]  # (c, 8, 6) parent branches
            aligned = self._align(self._ik[v][:, None, :, :], qu[:, :, None, :])  # (c, 8p, 8s, 6)
            L = self._metric(aligned - qu[:, :, None, :])
            L = np.where(self._valid[v][:, None, :], L, np.inf)
            order = np.argsort(L, axis=2, kind="stable")[:, :, :R]
            self._ord_tab[c0:c1] = order
            self._L_tab[c0:c1] = np.take_along_axis(L, order, axis=2)
            bits = ((rm.edge_branches[c0:c1, None].astype(np.int64) >> bidx) & 1).astype(bool)  # (c, 8)
            same = order == bidx[None, :, None]
            same &= np.take_along_axis(bits[:, None, :].repeat(NUM_BRANCHES, 1), order, axis=2)
            same &= self._valid[u][:, :, None]
            self._same_tab[c0:c1] = same
        self._L_tab.setflags(write=False)

    def _static_box_bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """World-axis bounds (B, 3) x 2 of the static boxes and the (link, box) pairs that count, if known."""
        boxes = getattr(self.collision, "static_boxes", None)
        pairs = getattr(self.collision, "static_pairs", None)
        if boxes is None or pairs is None or len(boxes) == 0:
            return None
        lo, hi = [], []
        for box in boxes:
            c, hs, yaw = np.asarray(box.center), np.asarray(box.size) / 2.0, float(box.yaw)
            ext = np.array(
                [
                    abs(math.cos(yaw)) * hs[0] + abs(math.sin(yaw)) * hs[1],
                    abs(math.sin(yaw)) * hs[0] + abs(math.cos(yaw)) * hs[1],
                    hs[2],
                ]
            )
            lo.append(c - ext)
            hi.append(c + ext)
        return np.array(lo), np.array(hi), np.asarray(pairs, dtype=bool)

    # ------------------------------------------------------------------------------------------ helpers
    def _align(self, q: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
        """2 pi-shift every joint of ``q`` (..., 6) next to ``q_ref`` (broadcastable), within the limits."""
        nearest = q + _TWO_PI * np.rint((q_ref - q) * (1.0 / _TWO_PI))
        nearest = np.where(nearest > self.q_max, nearest - _TWO_PI, nearest)
        nearest = np.where(nearest < self.q_min, nearest + _TWO_PI, nearest)
        bad = (nearest > self.q_max) | (nearest < self.q_min)
        return np.where(bad, q, nearest)

    def _metric(self, dq: np.ndarray) -> np.ndarray:
        """Straight-move length (...,) in seconds at full joint speed: max_j |dq_j| / qd_max_j."""
        return np.max(np.abs(dq) * self._inv_qd, axis=-1)

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        return np.all((q >= self.q_min - 1e-9) & (q <= self.q_max + 1e-9), axis=-1)

    def _static_bad(self, q: np.ndarray) -> np.ndarray:
        """Configurations (n, 6) in collision with the static scene or themselves, or beyond the limits."""
        bad = ~self._within_limits(q)
        sb = self._static_boxes
        if sb is None:
            need = np.arange(q.shape[0])
        else:
            blo, bhi, pairs = sb
            a, b, r = self.collision.robot_capsules(q)
            lo = np.minimum(a, b) - r[:, None]  # (n, L, 3)
            hi = np.maximum(a, b) + r[:, None]
            g = np.maximum(
                np.maximum(blo[None, None] - hi[:, :, None], lo[:, :, None] - bhi[None, None]), 0.0
            )
            gap = np.sqrt(np.einsum("nlbk,nlbk->nlb", g, g))
            near = (gap <= self.config.static_margin_m + 1e-9) & pairs[None]
            need = np.flatnonzero(near.any(axis=(1, 2)))
        if need.size:
            bad[need] |= self.collision.in_static_collision(q[need], margin_m=self.config.static_margin_m)
        bad |= self.collision.self_collision(q)
        return bad

    def _static_free(self, qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
        """Whether the straight joint moves qa[k] -> qb[k] ((M, 6) each) are free of the static scene and
        of self-collision at configurations at most ``check_step_rad`` apart (both ends included)."""
        M = qa.shape[0]
        if M == 0:
            return np.ones(0, dtype=bool)
        n = np.maximum(np.ceil(np.max(np.abs(qb - qa), axis=1) / self.config.check_step_rad), 1).astype(
            np.int64
        )
        idx = np.repeat(np.arange(M), n + 1)
        start = np.cumsum(n + 1) - (n + 1)
        frac = (np.arange(idx.shape[0]) - start[idx]) / n[idx]
        q = qa[idx] + frac[:, None] * (qb - qa)[idx]
        bad = self._static_bad(q)
        return np.bincount(idx, weights=bad, minlength=M) == 0

    def _static_cached(
        self,
        st: _States,
        par: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        q_par: np.ndarray,
        target: np.ndarray,
    ) -> np.ndarray:
        """Static check (1 free, -1 blocked) of moves the roadmap did not check, memoised per
        (node, branch, node, branch) when the move is the one between the stored branch configurations.

        The memo belongs to the planner (never the roadmap) and only ever gains entries that are pure
        functions of the roadmap, so concurrent queries may share it.
        """
        out = np.zeros(par.shape[0], dtype=np.int8)
        u = st.node[par]
        bu = st.branch[par]
        keys: list[tuple[int, int, int, int] | None] = [None] * par.shape[0]
        on = np.flatnonzero(u >= 0)
        if on.size:
            ref = self._ik[u[on], bu[on]]
            ref_t = self._align(self._ik[cv[on], b[on]], ref)
            same_move = np.abs((ref_t - ref) - (target[on] - q_par[on])).max(axis=1) <= 1e-9
            for i in on[same_move].tolist():
                key = (int(u[i]), int(bu[i]), int(cv[i]), int(b[i]))
                keys[i] = key
                hit = self._static_memo.get(key)
                if hit is not None:
                    out[i] = hit
        todo = np.flatnonzero(out == 0)
        if todo.size:
            res = np.where(self._static_free(q_par[todo], target[todo]), 1, -1).astype(np.int8)
            out[todo] = res
            for i, val in zip(todo.tolist(), res.tolist(), strict=True):
                if keys[i] is not None:
                    self._static_memo[keys[i]] = val
        return out

    def _heuristic_table(self, goal: int) -> np.ndarray:
        """h (N, 8): time lower bound from every node branch to the goal's nearest branch at cruise speed."""
        tab = self._h_cache.get(goal)
        if tab is None:
            tab = self._heuristic(self._ik.reshape(-1, 6), goal).reshape(-1, NUM_BRANCHES)
            tab.setflags(write=False)
            self._h_cache[goal] = tab
        return tab

    def _heuristic(self, q: np.ndarray, goal: int) -> np.ndarray:
        G = self._ik[goal][self._valid[goal]]
        inv = self._inv_qd / self.config.speed_fraction
        out = np.full(q.shape[0], np.inf)
        for g in G:  # at most 8 branches
            d = q - g
            d = np.abs(d - _TWO_PI * np.rint(d * (1.0 / _TWO_PI)))
            np.minimum(out, np.max(d * inv, axis=-1), out=out)
        return out

    def _separation(
        self,
        forecast: HumanForecast | None,
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
    ) -> _Separation:
        return _Separation(
            self.collision,
            forecast,
            self.config.ssm,
            self._parts,
            extra_m=extra_m,
            offsets=offsets,
            floor_m=floor_m,
        )

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

        Raises:
            ValueError: ``q_start`` is not a finite (6,) configuration.
            app.planning.roadmap.RoadmapError: unknown goal.
        """
        t0 = self._timer()
        q_start = np.asarray(q_start, dtype=np.float64).reshape(-1)
        if q_start.shape != (6,) or not np.all(np.isfinite(q_start)):
            raise ValueError(f"q_start must be a finite (6,) configuration, got {q_start!r}")
        goal_node = self.roadmap.resolve(goal)
        deadline = None if deadline_s is None else t0 + deadline_s
        cfg = self.config
        if not self._valid[goal_node].any():
            return PlanResult(False, None, "goal node has no valid IK branch", 0, self._timer() - t0)
        if not self._within_limits(q_start[None])[0]:
            return PlanResult(
                False, None, "start configuration outside the joint limits", 0, self._timer() - t0
            )
        start_sep = self._separation(forecast, extra_m=0.0)
        if not start_sep.check(q_start[None], np.array([float(t_start)]), np.zeros(1))[0]:
            reason = "start configuration violates the separation at t_start"
            return PlanResult(False, None, reason, 0, self._timer() - t0)
        attempts: list[tuple[float, ...]] = [(0.0,)]
        if forecast is not None and cfg.fallback_slack_s > 0:
            s = cfg.fallback_slack_s
            attempts.append((-0.25 * s, 0.0, 0.5 * s, s))
        expanded = 0
        reason = "no plan"
        for offsets in attempts:
            sep = self._separation(forecast, extra_m=cfg.corridor_margin_m, offsets=offsets)
            waypoints, n_exp, reason = self._search(
                q_start,
                float(t_start),
                sep,
                goal=goal_node,
                stop_time=None,
                hold_s=cfg.goal_hold_s,
                workers=workers,
                deadline=deadline,
            )
            expanded += n_exp
            if waypoints is None:
                break  # the time-robust check cannot succeed where the plain one failed
            done = self._finish(waypoints, qd0, forecast, hold_s=cfg.goal_hold_s)
            if done is not None:
                return PlanResult(True, done[0], "ok", expanded, self._timer() - t0, done[1])
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

        Stands still when that is safe for ``horizon_s`` + ``emergency_hold_s`` (reason ``"stay"``);
        otherwise searches until a state reaches ``t_start + horizon_s`` (paper: ``F + D``) whose
        configuration is safe to hold for ``emergency_hold_s``. When the robot already violates the separation
        at ``t_start``, moves are accepted that never bring it closer to the person than it is now.

        Args:
            q_start: Current configuration (6,) (rad).
            t_start: Now (s).
            forecast: The latest forecast: its pose and margin at ``t_start`` are held, growing at its rate.
            horizon_s: ``F + D`` (s).
            qd0: Current joint velocity (6,) (rad/s); the trajectory brakes from it.
            workers: States expanded per search step.
        """
        from app.prediction.forecast import HumanForecast

        t0 = self._timer()
        cfg = self.config
        q_start = np.asarray(q_start, dtype=np.float64).reshape(6)
        t_start = float(t_start)
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
            return PlanResult(True, traj.to_plan(), "stay", 0, self._timer() - t0, traj)
        # 2. Moving: search until t_stop; escape mode if the start already violates.
        d0 = float(self.collision.distance_to_human_paired(q_start[None], joints[None])[0])
        req0 = float(forecast_clearance(0.0, margin, cfg.ssm))
        floor = d0 - 1e-3 if d0 < req0 else None
        sep = self._separation(held, extra_m=cfg.corridor_margin_m, floor_m=floor)
        waypoints, expanded, reason = self._search(
            q_start, t_start, sep, goal=None, stop_time=t_stop, hold_s=hold_s, workers=workers, deadline=None
        )
        if waypoints is not None:
            done = self._finish(waypoints, qd0, held, hold_s=hold_s, floor_m=floor)
            if done is not None:
                return PlanResult(True, done[0], "ok", expanded, self._timer() - t0, done[1])
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

        The requirement at time t: surface distance robot-person >=
        :func:`app.planning.safety.forecast_clearance` (``S_r + S_s + C + Z_r + max(Z_d, margin)``) for the
        robot's speed at t (the largest speed of any capsule end point) and the forecast's margin at t; a
        configuration outside the joint limits counts as a violation too. Sampled every ``dt_s`` (default
        ``verify_dt_s``), both ends included. Returns None when there is no violation.
        """
        return self._verify(traj, forecast, t_from, t_to, dt_s=dt_s, static=False)

    def robot_speed(self, traj: Trajectory, t: np.ndarray) -> np.ndarray:
        """Robot speed (K,) in m/s at times ``t`` (K,): the largest speed of any capsule end point."""
        eps = 1e-4
        p0 = self._points_and_spheres(traj.q(t))[0]
        p1 = self._points_and_spheres(traj.q(t + eps))[0]
        return np.max(np.linalg.norm(p1 - p0, axis=-1), axis=-1) / eps

    # ------------------------------------------------------------------------------------------ fit & verify
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
            moving = np.flatnonzero((ts >= traj.t_start) & (ts <= traj.t_end))
            if moving.size:
                bad[moving] |= self._static_bad(q[moving])
        if forecast is not None:
            v = self.robot_speed(traj, ts)
            joints, margins = forecast.poses_at(ts)
            d = self.collision.distance_to_human_paired(q, joints)
            req = forecast_clearance(v, margins, self.config.ssm)
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
            logger.debug("fitted trajectory violates at t=%.3f (%.3f..%.3f)", viol, traj.t_start, traj.t_end)
            return None
        return traj.to_plan(_map_nodes(waypoints, traj)), traj

    # ------------------------------------------------------------------------------------------ search
    def _search(
        self,
        q_start: np.ndarray,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        stop_time: float | None,
        hold_s: float,
        workers: int,
        deadline: float | None,
    ) -> tuple[Plan | None, int, str]:
        """The time-variant A*. Returns (waypoints or None, expanded states, reason)."""
        cfg = self.config
        N = self.roadmap.num_nodes
        workers = max(int(workers), 1)
        states = _States(256, self._n_pts, self._n_caps)
        pts0, cen0, rad0 = self._points_and_spheres(q_start[None])
        one = np.ones(1)
        sid0 = int(
            states.add(
                node=-one.astype(np.int64),
                branch=-one.astype(np.int64),
                t=one * t_start,
                u=one * 0.0,
                q=q_start[None],
                parent=-one.astype(np.int64),
                dep=one * t_start,
                pts=pts0,
                cen=cen0,
                rad=rad0,
            )[0]
        )
        Q = _Query(
            sep=sep,
            goal=goal,
            stop_time=stop_time,
            hold_s=hold_s,
            f=cfg.speed_fraction,
            A=self._A,
            AT=np.full(N, np.inf),
            states=states,
            h_tab=None if goal is None else self._heuristic_table(goal),
        )
        h0 = 0.0 if goal is None else float(self._heuristic(q_start[None], goal)[0])
        if stop_time is not None:
            h0 = max(stop_time - t_start, 0.0)
        heap: list[tuple[float, float, int]] = [(t_start + h0, -t_start, sid0)]
        AT = Q.AT
        expanded = 0
        while heap:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            seen: set[int] = set()
            while heap and len(batch) < workers:
                entry = heapq.heappop(heap)
                sid = entry[2]
                node = int(states.node[sid])
                if node >= 0 and (states.t[sid] > AT[node] + _EPS_T or node in seen):
                    continue  # superseded by a better arrival
                if (goal is not None and node == goal) or (
                    stop_time is not None and states.t[sid] >= stop_time
                ):
                    if batch:  # states popped before it (f <= its f) may still improve it: expand them first
                        heapq.heappush(heap, entry)
                        break
                    return self._reconstruct(states, sid), expanded, "ok"
                seen.add(node)
                batch.append(sid)
            if not batch:
                break
            expanded += len(batch)
            new = self._expand(Q, np.array(batch, dtype=np.int64))
            if new.size:
                tv = states.t[new]
                if stop_time is not None:
                    hv = np.maximum(stop_time - tv, 0.0)
                elif Q.h_tab is not None:
                    hv = Q.h_tab[states.node[new], states.branch[new]]
                else:
                    hv = np.zeros(new.size)
                for sid, fv, tt in zip(new.tolist(), (tv + hv).tolist(), tv.tolist(), strict=True):
                    heapq.heappush(heap, (fv, -tt, sid))
        what = "goal" if goal is not None else "the emergency horizon"
        return None, expanded, f"{what} unreachable: no safe path found after {expanded} expansions"

    def _candidates(
        self, Q: _Query, batch: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Candidate moves of a batch: (parent state (M,), node (M,), branches (M, R), lengths (M, R),
        roadmap-checked (M, R))."""
        st = Q.states
        nodes = st.node[batch]
        on = batch[nodes >= 0]
        parts = []
        if on.size:
            rm = self.roadmap
            u = st.node[on]
            starts = rm.indptr[u]
            cnt = rm.indptr[u + 1] - starts
            par = np.repeat(on, cnt)
            offs = np.cumsum(cnt) - cnt
            e = np.repeat(starts - offs, cnt) + np.arange(int(cnt.sum()))
            bpar = st.branch[par]
            parts.append(
                (
                    par,
                    rm.indices[e],
                    self._ord_tab[e, bpar].astype(np.int64),
                    self._L_tab[e, bpar].astype(np.float64),
                    self._same_tab[e, bpar],
                )
            )
        for sid in batch[nodes < 0].tolist():
            q = st.q[sid]
            aligned = self._align(self._ik, q[None, None, :])
            L = np.where(self._valid, self._metric(aligned - q), np.inf)
            best = L.min(axis=1)
            k = min(self.config.start_neighbors, int(np.isfinite(best).sum()))
            if k == 0:
                continue
            cv = np.argpartition(best, k - 1)[:k]
            order = np.argsort(L[cv], axis=1, kind="stable")[:, : self._R]
            parts.append(
                (
                    np.full(k, sid),
                    cv,
                    order,
                    np.take_along_axis(L[cv], order, axis=1),
                    np.zeros(order.shape, bool),
                )
            )
        if not parts:
            z = np.zeros(0, dtype=np.int64)
            return (
                z,
                z,
                np.zeros((0, self._R), np.int64),
                np.zeros((0, self._R)),
                np.zeros((0, self._R), bool),
            )
        return tuple(np.concatenate(x) for x in zip(*parts, strict=True))  # type: ignore[return-value]

    def _expand(self, Q: _Query, batch: np.ndarray) -> np.ndarray:
        """Expand a batch of states; returns the ids of the new states."""
        cfg = self.config
        st = Q.states
        par, cv, order, L, same = self._candidates(Q, batch)
        M = cv.shape[0]
        if M == 0:
            return np.zeros(0, dtype=np.int64)
        R = order.shape[1]
        t_par = st.t[par]
        end_rest = np.zeros(M, dtype=bool) if Q.goal is None else (cv == Q.goal)
        u0 = np.broadcast_to(st.u[par][:, None], (M, R))
        finite = np.isfinite(L)
        Lf = np.where(finite, L, 0.0)
        h, u_end, peak = _profile(u0, Lf, Q.f, Q.A, end_rest[:, None])
        h = np.where(Lf > 1e-12, np.maximum(h, cfg.min_edge_s), 0.0)
        arrival = t_par[:, None] + h
        alive = finite & (arrival < Q.AT[cv][:, None] - _EPS_T)
        resolved = ~alive.any(axis=1)
        static_state = np.where(same, 1, 0).astype(np.int8)  # 1 free, 0 unknown, -1 blocked
        acc: list[tuple[np.ndarray, ...]] = []
        for r in range(R):
            idx = np.flatnonzero(~resolved & alive[:, r])
            if idx.size == 0:
                continue
            b = order[idx, r]
            q_par = st.q[par[idx]]
            target = self._align(self._ik[cv[idx], b], q_par)
            ss = static_state[idx, r]
            chk = np.flatnonzero(ss == 1)
            if chk.size:  # the roadmap checked the move from its own representative: the same move?
                ref = self._ik[st.node[par[idx[chk]]], b[chk]]
                ref_t = self._align(self._ik[cv[idx[chk]], b[chk]], ref)
                diff = np.abs((ref_t - ref) - (target[chk] - q_par[chk])).max(axis=1) > 1e-6
                ss[chk[diff]] = 0
            unk = np.flatnonzero(ss == 0)
            if unk.size:
                ss[unk] = self._static_cached(
                    st, par[idx[unk]], cv[idx[unk]], b[unk], q_par[unk], target[unk]
                )
            static_state[idx, r] = ss
            keep = ss == 1
            if not np.any(keep):
                continue
            idx, b, target = idx[keep], b[keep], target[keep]
            ok = self._moves_ok(
                Q,
                par[idx],
                cv[idx],
                b,
                target,
                t_par[idx],
                h[idx, r],
                u0[idx, r],
                Lf[idx, r],
                end_rest[idx],
                peak[idx, r],
            )
            good = np.flatnonzero(ok)
            if good.size:
                g = idx[good]
                acc.append((par[g], cv[g], b[good], target[good], arrival[g, r], u_end[g, r], t_par[g]))
                resolved[g] = True
        # slower: the nearest statically free branch at a lower cruise speed (a smaller S_r + S_s)
        if Q.sep.forecast is not None:
            for f_slow in cfg.slow_speed_fractions:
                idx = np.flatnonzero(~resolved & alive[:, 0] & (static_state[:, 0] == 1))
                if idx.size == 0 or f_slow >= Q.f:
                    break
                b = order[idx, 0]
                target = self._align(self._ik[cv[idx], b], st.q[par[idx]])
                u0s = np.minimum(st.u[par[idx]], f_slow)
                hs, ues, pks = _profile(u0s, Lf[idx, 0], f_slow, Q.A, end_rest[idx])
                hs = np.where(Lf[idx, 0] > 1e-12, np.maximum(hs, cfg.min_edge_s), 0.0)
                arr = t_par[idx] + hs
                live = arr < Q.AT[cv[idx]] - _EPS_T
                idx, b, target, u0s, hs, ues, pks, arr = (
                    x[live] for x in (idx, b, target, u0s, hs, ues, pks, arr)
                )
                if idx.size == 0:
                    break
                ok = self._moves_ok(
                    Q,
                    par[idx],
                    cv[idx],
                    b,
                    target,
                    t_par[idx],
                    hs,
                    u0s,
                    Lf[idx, 0],
                    end_rest[idx],
                    pks,
                    f=f_slow,
                )
                good = np.flatnonzero(ok)
                if good.size:
                    g = idx[good]
                    acc.append((par[g], cv[g], b[good], target[good], arr[good], ues[good], t_par[g]))
                    resolved[g] = True
        pending = np.flatnonzero(~resolved)
        if pending.size and cfg.max_wait_s > 0 and Q.sep.forecast is not None:
            got = self._try_waits(Q, pending, par, cv, order, L, static_state, end_rest)
            if got is not None:
                acc.append(got)
        if not acc:
            return np.zeros(0, dtype=np.int64)
        c_par, c_v, c_b, c_q, c_t, c_u, c_dep = (np.concatenate(x) for x in zip(*acc, strict=True))
        # relax: the earliest arrival per node, only where it improves AT
        o = np.lexsort((c_t, c_v))
        first = np.ones(o.shape[0], dtype=bool)
        first[1:] = c_v[o][1:] != c_v[o][:-1]
        o = o[first]
        o = o[c_t[o] < Q.AT[c_v[o]] - _EPS_T]
        if o.size == 0:
            return np.zeros(0, dtype=np.int64)
        c_v, c_b = c_v[o], c_b[o]
        Q.AT[c_v] = c_t[o]
        return st.add(
            node=c_v,
            branch=c_b,
            t=c_t[o],
            u=c_u[o],
            q=c_q[o],
            parent=c_par[o],
            dep=c_dep[o],
            pts=self._pts_all[c_v, c_b],
            cen=self._cen_all[c_v, c_b],
            rad=self._rad_all[c_v, c_b],
        )

    def _moves_ok(
        self,
        Q: _Query,
        par: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        peak: np.ndarray,
        *,
        f: float | None = None,
    ) -> np.ndarray:
        """Check moves (and the hold at their end where required) against the forecast; boolean (M,).

        ``f`` is the cruise speed the moves were timed with (default the query's)."""
        M = par.shape[0]
        if Q.sep.forecast is None or M == 0:
            return np.ones(M, dtype=bool)
        cfg = self.config
        st = Q.states
        q_a = st.q[par]
        dq = target - q_a
        # robot speed for S_r + S_s: the largest chord speed of the capsule points, average -> peak, x factor
        chord = np.max(np.linalg.norm(self._pts_all[cv, b] - st.pts[par], axis=-1), axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(L > 1e-12, np.maximum(peak * h / np.maximum(L, 1e-12), 1.0), 1.0)
            v_move = np.where(h > 0, chord / h * ratio, 0.0) * cfg.speed_factor
        # samples: the move every sample_dt_s (its end included), then the hold
        n = np.maximum(np.ceil(h / cfg.sample_dt_s - 1e-9), 1).astype(np.int64)
        if Q.goal is None:
            hold = np.ones(M, dtype=bool) if Q.hold_s > 0 else np.zeros(M, dtype=bool)
        else:
            hold = cv == Q.goal
        n_hold_1 = max(math.ceil(Q.hold_s / cfg.sample_dt_s - 1e-9), 0)
        n_hold = np.where(hold, n_hold_1, 0)
        tot = n + n_hold
        owner = np.repeat(np.arange(M), tot)
        i = np.arange(owner.shape[0]) - np.repeat(np.cumsum(tot) - tot, tot) + 1
        n_o, h_o = n[owner], h[owner]
        in_move = i <= n_o
        tau = np.where(in_move, i / n_o * h_o, h_o)
        frac = _profile_fraction(tau, u0[owner], L[owner], h_o, Q.f if f is None else f, Q.A, end_rest[owner])
        frac = np.where(in_move, frac, 1.0)
        q = q_a[owner] + frac[:, None] * dq[owner]
        t = t_dep[owner] + tau + np.where(in_move, 0.0, (i - n_o) * (Q.hold_s / max(n_hold_1, 1)))
        v = np.where(in_move, v_move[owner], 0.0)
        # capsule l lies within its start sphere grown by frac * T_l and its end sphere grown by
        # (1 - frac) * T_l, T_l = how far joints 1..J(l) can carry it; take the smaller sphere
        cum = np.concatenate([np.zeros((M, 1)), np.cumsum(np.abs(dq) * self._lever, axis=1)], axis=1)
        travel = cum[:, self._moved_by]  # (M, L)
        fo = frac[:, None]
        ra = st.rad[par][owner] + fo * travel[owner]
        rb = self._rad_all[cv, b][owner] + (1.0 - fo) * travel[owner]
        use_a = ra <= rb
        cen = np.where(use_a[..., None], st.cen[par][owner], self._cen_all[cv, b][owner])
        rad = np.where(use_a, ra, rb)
        ok_s = Q.sep.check(q, t, v, cen, rad)
        return np.bincount(owner, weights=~ok_s, minlength=M) == 0

    def _try_waits(
        self,
        Q: _Query,
        pending: np.ndarray,
        par: np.ndarray,
        cv: np.ndarray,
        order: np.ndarray,
        L: np.ndarray,
        static_state: np.ndarray,
        end_rest: np.ndarray,
    ) -> tuple[np.ndarray, ...] | None:
        """Wait at the parent, then move: all (candidate, branch, wait step) combinations in one check."""
        cfg = self.config
        st = Q.states
        K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
        if K < 1:
            return None
        # how long each parent can stand still (robot at rest: speed 0)
        todo = [p for p in np.unique(par[pending]).tolist() if p not in Q.wait_safe_until]
        if todo:
            sub = max(1, math.ceil(cfg.wait_step_s / cfg.sample_dt_s - 1e-9))
            n = K * sub
            tp = np.array(todo, dtype=np.int64)
            ts = st.t[tp][:, None] + (cfg.wait_step_s / sub) * np.arange(1, n + 1)[None, :]
            rep = np.repeat(tp, n)
            ok = Q.sep.check(st.q[rep], ts.reshape(-1), np.zeros(rep.size), st.cen[rep], st.rad[rep])
            ok = ok.reshape(tp.size, n)
            for j, p in enumerate(todo):
                bad = np.flatnonzero(~ok[j])
                Q.wait_safe_until[p] = float(ts[j, bad[0]]) if bad.size else math.inf
        R = 1  # waiting is tried with the nearest branch only
        P = pending.size
        cand = np.repeat(pending, R * K)
        rank = np.tile(np.repeat(np.arange(R), K), P)
        kk = np.tile(np.arange(1, K + 1), P * R)
        t_go = st.t[par[cand]] + kk * cfg.wait_step_s
        safe_until = np.array([Q.wait_safe_until[p] for p in par[cand].tolist()])
        Lc = L[cand, rank]
        finite = np.isfinite(Lc)
        Lf = np.where(finite, Lc, 0.0)
        u0 = np.zeros(cand.shape[0])
        h, u_end, peak = _profile(u0, Lf, Q.f, Q.A, end_rest[cand])
        h = np.where(Lf > 1e-12, np.maximum(h, cfg.min_edge_s), 0.0)
        arrival = t_go + h
        live = np.flatnonzero(
            finite
            & (static_state[cand, rank] == 1)
            & (t_go < safe_until - _EPS_T)
            & (arrival < Q.AT[cv[cand]] - _EPS_T)
        )
        if live.size == 0:
            return None
        c, r = cand[live], rank[live]
        b = order[c, r]
        target = self._align(self._ik[cv[c], b], st.q[par[c]])
        ok = self._moves_ok(
            Q, par[c], cv[c], b, target, t_go[live], h[live], u0[live], Lf[live], end_rest[c], peak[live]
        )
        if not np.any(ok):
            return None
        sel = live[ok]
        c, r, b, target = c[ok], r[ok], b[ok], target[ok]
        # per candidate: the shortest wait, then the nearest branch (sel is ordered by candidate, rank, k)
        o = np.lexsort((r, kk[sel], c))
        first = np.ones(o.shape[0], dtype=bool)
        first[1:] = c[o][1:] != c[o][:-1]
        o = o[first]
        s = sel[o]
        return par[c[o]], cv[c[o]], b[o], target[o], arrival[s], u_end[s], t_go[s]

    def _reconstruct(self, states: _States, sid: int) -> Plan:
        chain = []
        s = sid
        while s >= 0:
            chain.append(s)
            s = int(states.parent[s])
        chain.reverse()
        if len(chain) > 1:
            a, b = chain[0], chain[1]
            if states.t[b] <= states.t[a] + _EPS_T and np.allclose(states.q[a], states.q[b], atol=1e-12):
                chain = chain[1:]  # the start is a roadmap node: one waypoint, labelled with the node
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
