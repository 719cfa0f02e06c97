"""Time-variant A* over the static roadmap (sequential and batched-parallel), emergency plans, validity check.

Paper, section II-A, and where this goes further:

- **State.** Per roadmap node ``v`` the search keeps the arrival time ``AT(v)``; every state is an immutable
  record of the search (node, IK branch, time, path speed, parent, departure, and its configuration
  ``Cfg(v)`` once checked), so a plan is rebuilt from exactly the configurations and times that were checked.
  The roadmap is never written to.
- **Expansion u -> v.** The IK branches of ``v`` (each shifted by multiples of 2 pi next to ``Cfg(u)``) are
  ordered by the time a straight joint move needs (precomputed per edge and branch); the nearest is tried
  first, the others (at most ``max_branch_tries``) when it fails. A move between the same branch at both ends
  uses the roadmap's static edge check; any other move (another branch, the start connection) is checked
  against the static scene on the fly (memoised).
- **Lazy checking.** Successors are generated in plain Python, timed and pushed *unchecked*; a move is
  checked only when its state is popped (its key ``t + h`` is a lower bound of any checked path through it,
  so the order is still A*'s). This checks a few moves per expansion instead of all of them.
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
- **Slower, then waiting (safe-interval style).** When the branches are blocked at the cruise speed, the
  nearest one is tried at ``slow_speed_fractions`` (less ``S_r + S_s``), and after waiting at ``u`` in steps
  of ``wait_step_s`` up to ``max_wait_s`` (if standing still there is itself safe). Without a person the
  search is plain A*.
- **Pruning.** When the person blocks every goal branch for good after some time (their last pose held, the
  margin at its cap), states that cannot arrive before it (by the admissible heuristic) are not pushed; a
  goal blocked from the start fails at once. Plans longer than ``max_plan_s`` are not searched for.
- **Parallel.** ``workers = N`` pops up to N states per step and checks all their moves, time samples and
  waits in one vectorised call (the batched equivalent of the paper's N threads taking nodes from the open
  list in turn; in CPython threads would serialise on the interpreter lock). ``AT`` is updated only when a
  checked arrival improves it and a goal state is accepted only when nothing popped before it is pending, so
  the validity guarantees and the result are those of the sequential search (up to ties); a node may be
  expanded again when a later batch improves it.
- **Broad phase.** Whole moves far from the person over their time window, then single samples far from
  every body part, are passed without forward kinematics (bounding spheres of the robot capsules grown by
  how far the joints can carry them, against boxes around the body parts); only close capsule pairs get the
  exact capsule distance.
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
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

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
        heuristic_weight: ``w`` of the key ``t + w h``: 1 is A* (time-optimal among the checked moves);
            ``w > 1`` is weighted A* (plans at most ``w`` times longer, usually far fewer expansions).
        slow_speed_fractions: When every branch is blocked at the cruise speed, the nearest one is tried
            again at these lower cruise speeds (a slower robot needs less ``S_r + S_s``) before waiting.
        goal_hold_s: After arriving at the goal the robot must be able to stand there this long (s).
        start_neighbors: Number of roadmap nodes the start configuration is connected to.
        check_step_rad: Largest joint step (rad) between configurations checked against the static scene.
        static_margin_m: Clearance (m) from the static scene for on-the-fly checks (as the roadmap's).
        max_expansions: Bound on expanded states per search.
        max_plan_s: Plans that cannot reach the goal within this long (s, by the admissible heuristic) are
            not searched for (the supervisor replans every frame; a longer detour is not worth the time).
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
    heuristic_weight: float = 1.0
    slow_speed_fractions: tuple[float, ...] = (0.2,)
    goal_hold_s: float = 0.3
    start_neighbors: int = 8
    check_step_rad: float = 0.05
    static_margin_m: float = 0.0
    max_expansions: int = 20000
    max_plan_s: float = 8.0
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
        if self.heuristic_weight < 1.0:
            raise ValueError(f"PlannerConfig.heuristic_weight must be >= 1, got {self.heuristic_weight}")
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
    return np.minimum(np.maximum(np.where(L > 1e-12, pos / np.maximum(L, 1e-12), 1.0), 0.0), 1.0)


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
    """Pass/fail of robot samples (and whole moves) against a forecast person.

    Three conservative stages: (0) a whole move: one sphere per robot capsule that contains it during the move
    against the body-part boxes over the move's time window; (1) each sample: a sphere per robot capsule
    (known without forward kinematics, see :meth:`Planner._moves_ok`) against the part boxes at that time;
    (2) for the (sample, robot capsule, part) triples still close, the exact distance between the robot
    capsule and each person capsule of the part (:func:`app.planning.collision.segment_distance`). The part
    boxes are precomputed at the forecast's own samples (a pose between two samples is a blend of them, so
    it lies in the union of their boxes; beyond the horizon the last pose is held).
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
        if forecast is None:
            return
        joints = forecast.joints  # (H, J, 3)
        self._human_r = np.asarray(model.human_capsules(joints[:1])[2], dtype=np.float64)
        P = self.member.shape[0]
        part_r = np.array(
            [
                self._human_r[self.caps_flat[self.caps_start[p] : self.caps_start[p + 1]]].max(initial=0.0)
                for p in range(P)
            ]
        )
        m4 = self.member[None, :, :, None]
        lo = np.where(m4, joints[:, None], np.inf).min(axis=2) - part_r[:, None]  # (H, P, 3)
        hi = np.where(m4, joints[:, None], -np.inf).max(axis=2) + part_r[:, None]
        # sparse table of unions over index ranges [i, i + 2^k)
        self._lo_tab, self._hi_tab = [lo], [hi]
        k = 1
        while (1 << k) <= lo.shape[0]:
            plo, phi = self._lo_tab[-1], self._hi_tab[-1]
            half = 1 << (k - 1)
            self._lo_tab.append(np.minimum(plo[:-half], plo[half:]))
            self._hi_tab.append(np.maximum(phi[:-half], phi[half:]))
            k += 1
        self._times = forecast.times
        self._cap = max(forecast.max_margin_m, float(forecast.margins.max()))
        # boxes around two consecutive samples (a sample's own box when there is only one)
        self._lo_pair = self._lo_tab[1] if len(self._lo_tab) > 1 else lo
        self._hi_pair = self._hi_tab[1] if len(self._hi_tab) > 1 else hi

    def _boxes(self, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Part boxes (n, P, 3) x 2 that contain the person over each window [t0, t1] (t0 <= t1)."""
        times = self._times
        H = times.shape[0]
        i0 = np.minimum(np.maximum(np.searchsorted(times, t0, side="right") - 1, 0), H - 1)
        i1 = np.minimum(np.searchsorted(times, t1, side="left"), H - 1)
        i1 = np.maximum(i1, i0)
        span = i1 - i0 + 1
        k = np.floor(np.log2(span)).astype(np.int64)
        lo = np.empty((t0.shape[0], *self._lo_tab[0].shape[1:]))
        hi = np.empty_like(lo)
        for kk in np.unique(k).tolist():
            sel = np.flatnonzero(k == kk)
            a, b = i0[sel], i1[sel] - (1 << kk) + 1
            lo[sel] = np.minimum(self._lo_tab[kk][a], self._lo_tab[kk][b])
            hi[sel] = np.maximum(self._hi_tab[kk][a], self._hi_tab[kk][b])
        return lo, hi

    def _margins(self, t: np.ndarray) -> np.ndarray:
        """The forecast's margins at times ``t`` (as :meth:`HumanForecast.poses_at`, without the poses)."""
        fc = self.forecast
        assert fc is not None
        m = np.interp(t, fc.times, fc.margins)
        if fc.growth_mps > 0.0:
            m = np.minimum(m + fc.growth_mps * np.maximum(t - fc.times[-1], 0.0), self._cap)
        return m

    def _required(self, v: np.ndarray, t: np.ndarray) -> np.ndarray:
        req = forecast_clearance(v, self._margins(t), self.ssm) + self.extra_m
        return req if self.floor_m is None else np.minimum(req, self.floor_m)

    def near_moves(
        self, cen: np.ndarray, rad: np.ndarray, t0: np.ndarray, t1: np.ndarray, v: np.ndarray
    ) -> np.ndarray:
        """Stage 0: (M,) bool, False where a move certainly keeps the separation.

        ``cen`` (M, L, 3) / ``rad`` (M, L): spheres that contain each robot capsule during the whole move,
        which lasts from ``t0`` to ``t1`` at robot speed ``v`` (m/s)."""
        M = cen.shape[0]
        if self.forecast is None or M == 0:
            return np.zeros(M, dtype=bool)
        lo_off, hi_off = min(self.offsets), max(self.offsets)
        lo, hi = self._boxes(t0 + lo_off, t1 + hi_off)
        # the margin only grows with time: the window's end needs the most
        req = np.maximum(self._required(v, t1 + hi_off), self._required(np.zeros(M), t0 + lo_off))
        c = cen[:, :, None, :]
        g = np.maximum(np.maximum(lo[:, None] - c, c - hi[:, None]), 0.0)  # (M, L, P, 3)
        gap = np.sqrt(np.einsum("mlpk,mlpk->mlp", g, g)) - rad[:, :, None]
        return (gap < req[:, None, None]).any(axis=(1, 2))

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
        req = self._required(v, t)
        n = q.shape[0]
        self.samples += n
        hr = self._human_r
        if cen is not None and rad is not None:
            i = np.searchsorted(self._times, t, side="right") - 1
            np.maximum(i, 0, out=i)
            np.minimum(i, self._lo_pair.shape[0] - 1, out=i)
            lo, hi = self._lo_pair[i], self._hi_pair[i]
            c = cen[:, :, None, :]  # (n, L, 1, 3)
            g = np.maximum(np.maximum(lo[:, None] - c, c - hi[:, None]), 0.0)  # (n, L, P, 3)
            gap = np.sqrt(np.einsum("nlpk,nlpk->nlp", g, g)) - rad[:, :, None]
            si, li, pi = np.nonzero(gap < req[:, None, None])
        else:
            si = li = pi = None
        ok = np.ones(n, dtype=bool)
        if si is not None and si.size == 0:
            return ok.reshape(n_off, S).all(axis=0) if n_off > 1 else ok
        from app.planning.collision import segment_distance

        us, inv = np.unique(np.arange(n) if si is None else si, return_inverse=True)
        joints, _ = self.forecast.poses_at(t[us])
        ra, rb, rr = self.model.robot_capsules(q[us])
        ha, hb, _ = self.model.human_capsules(joints)
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
        self._rev_graph = self._reverse_move_graph()
        self._h_cache: dict[int, np.ndarray] = {}
        self._h_lists: dict[int, list[list[float]]] = {}
        self._static_memo: dict[tuple[int, int, int, int], int] = {}
        self._succ_memo: dict[int, list[tuple[int, list[tuple[int, float, bool]]]]] = {}
        for node in roadmap.station_nodes.values():
            if self._valid[node].any():
                self._heuristic_table(node)

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
        self._L_tab = np.full((E, NUM_BRANCHES, R), np.inf)
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
        u: np.ndarray,
        bu: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        q_par: np.ndarray,
        target: np.ndarray,
    ) -> np.ndarray:
        """Static check (1 free, -1 blocked) of moves q_par -> target that the roadmap did not check, from
        node ``u`` at branch ``bu`` (-1: the start) to node ``cv`` at branch ``b``; memoised per
        (node, branch, node, branch) when the move is the one between the stored branch configurations.

        The memo belongs to the planner (never the roadmap) and only ever gains entries that are pure
        functions of the roadmap, so concurrent queries may share it.
        """
        out = np.zeros(u.shape[0], dtype=np.int8)
        keys: list[tuple[int, int, int, int] | None] = [None] * u.shape[0]
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
        """h (N, 8): time lower bound (s) from every node branch to the goal at cruise speed.

        The larger of two admissible bounds: the straight joint-space move to the goal's nearest branch, and
        the static time-to-go over the search's own moves (:meth:`_static_to_go`, a backward Dijkstra from
        the goal's branches). A branch from which no move sequence reaches the goal gets +inf (pruned).
        """
        tab = self._h_cache.get(goal)
        if tab is None:
            straight = self._heuristic(self._ik.reshape(-1, 6), goal)
            tab = np.maximum(straight, self._static_to_go(goal)).reshape(-1, NUM_BRANCHES)
            tab.setflags(write=False)
            self._h_cache[goal] = tab
            self._h_lists[goal] = tab.tolist()
        return tab

    def _reverse_move_graph(self) -> csr_matrix:
        """The search's moves (node, branch) -> (node, branch) as a sparse matrix of the *reversed* graph:
        entry [dst, src] = the move's length (s at full joint speed, :attr:`_L_tab`) / cruise speed."""
        rm = self.roadmap
        E, R = self._L_tab.shape[0], self._R
        S = rm.num_nodes * NUM_BRANCHES
        src_node = np.repeat(np.arange(rm.num_nodes), np.diff(rm.indptr))
        src = (src_node[:, None, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)[None, :, None]).repeat(R, 2)
        dst = rm.indices[:, None, None] * NUM_BRANCHES + self._ord_tab.astype(np.int64)
        # a hair shorter than the timed moves: round-off never makes the bound exceed a path's duration
        cost = self._L_tab * ((1.0 - 1e-12) / self.config.speed_fraction)
        keep = np.isfinite(cost) & self._valid[src_node][:, :, None]
        assert src.shape == dst.shape == cost.shape == (E, NUM_BRANCHES, R)
        return csr_matrix((cost[keep], (dst[keep], src[keep])), shape=(S, S))

    def _static_to_go(self, goal: int) -> np.ndarray:
        """Static time-to-go (N * 8,) in s from every node branch to any valid branch of ``goal`` over the
        moves the search can take (nearest ``max_branch_tries`` branches per edge), each timed at the cruise
        speed without acceleration: a lower bound of any search path's duration (its moves last at least
        their length / cruise speed), +inf where the goal cannot be reached."""
        sources = goal * NUM_BRANCHES + np.flatnonzero(self._valid[goal])
        if sources.size == 0:
            return np.full(self.roadmap.num_nodes * NUM_BRANCHES, np.inf)
        return dijkstra(self._rev_graph, directed=True, indices=sources, min_only=True)

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
        d0 = float(self.collision.distance_to_human_paired(q_start[None], joints[None])[0])
        # 1. Standing still (braking from qd0) when that is safe.
        at_rest = qd0 is None or not np.any(np.asarray(qd0) != 0.0)
        if at_rest:
            # the distance to a held person is constant; the requirement only grows with the margin
            _, m_end = held.pose_at(t_stop + hold_s)
            if d0 >= float(forecast_clearance(0.0, m_end, cfg.ssm)) and self._within_limits(q_start[None])[0]:
                traj = Trajectory(np.array([t_start]), q_start[None], np.zeros((1, 6)))
                return PlanResult(True, traj.to_plan(), "stay", 0, self._timer() - t0, traj)
        else:
            stay = Plan(times=np.array([t_start]), q=q_start[None], nodes=np.array([-1]))
            traj = self._fit(stay, qd0)
            if (
                traj is not None
                and self._verify(traj, held, t_start, max(t_stop, traj.t_end) + hold_s) is None
            ):
                return PlanResult(True, traj.to_plan(), "stay", 0, self._timer() - t0, traj)
        # 2. Moving: search until t_stop; escape mode if the start already violates.
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
    def _succ(self, u: int, b: int) -> list[tuple[int, list[tuple[int, float, bool]]]]:
        """Successors of node ``u`` at branch ``b``: (node, [(branch, length, roadmap-checked)] nearest
        first, at most ``max_branch_tries``), from the precomputed tables; memoised per planner."""
        key = u * NUM_BRANCHES + b
        got = self._succ_memo.get(key)
        if got is None:
            rm = self.roadmap
            a, z = int(rm.indptr[u]), int(rm.indptr[u + 1])
            order = self._ord_tab[a:z, b].tolist()
            length = self._L_tab[a:z, b].astype(np.float64).tolist()
            same = self._same_tab[a:z, b].tolist()
            got = []
            for i, v in enumerate(rm.indices[a:z].tolist()):
                opts = [
                    (o, ln, s) for o, ln, s in zip(order[i], length[i], same[i], strict=True) if ln < math.inf
                ]
                if opts:
                    got.append((v, opts))
            self._succ_memo[key] = got
        return got

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
        """Lazy time-variant A*. Returns (waypoints or None, validated expansions, reason).

        Successor moves are generated in plain Python from the precomputed tables and pushed unchecked,
        timed by the path-speed profile; a move is checked (static scene where the roadmap did not check it,
        forecast person, wait, goal hold) only when its state is popped, ``workers`` states at a time in one
        vectorised check. A failed move pushes its alternatives: the next branches, the slower speeds, the
        waits. The f-values of unchecked states are their times + the heuristic, so the order and the
        result are those of A* over the checked moves.
        """
        cfg = self.config
        N = self.roadmap.num_nodes
        f = cfg.speed_fraction
        W = max(int(workers), 1)
        run = _Run(self, q_start, t_start, sep, goal=goal, stop_time=stop_time, hold_s=hold_s)
        if goal is not None:
            self._heuristic_table(goal)
        h_tab = None if goal is None else self._h_lists[goal]

        w_h = cfg.heuristic_weight

        def heur(node: int, branch: int, t: float) -> float:
            if stop_time is not None:
                return max(stop_time - t, 0.0)
            return 0.0 if h_tab is None else w_h * h_tab[node][branch]

        # the latest arrival after which the person blocks the goal for good (an admissible prune: with a
        # heuristic weight w > 1 the pushed key t + w h >= t + h, so compare t + h itself)
        t_last = math.inf if goal is None else self._latest_goal_arrival(sep, goal, t_start, hold_s)
        t_last = min(t_last, t_start + cfg.max_plan_s)
        AT = [math.inf] * N
        heap: list[tuple[float, float, int]] = []

        def push(sid: int) -> None:
            t = run.t[sid]
            hv = heur(run.node[sid], run.branch[sid], t)
            if t + hv / w_h <= t_last:
                heapq.heappush(heap, (t + hv, -t, sid))

        for sid in run.start_options():
            push(sid)
        expanded = 0
        while heap:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            while heap and len(batch) < W:
                entry = heapq.heappop(heap)
                sid = entry[2]
                node = run.node[sid]
                if run.t[sid] >= AT[node] - _EPS_T:
                    continue  # a checked state reached this node no later
                final = (node == goal) or (stop_time is not None and run.t[sid] >= stop_time)
                if final and batch:  # states popped before it (f <= its f) may still improve it
                    heapq.heappush(heap, entry)
                    break
                batch.append(sid)
                if final:
                    break
            if not batch:
                break
            ok = run.check(batch)
            for sid, good in zip(batch, ok, strict=True):
                node = run.node[sid]
                if not good:
                    for alt in run.alternatives(sid, AT):
                        push(alt)
                    continue
                if run.t[sid] >= AT[node] - _EPS_T:
                    continue
                AT[node] = run.t[sid]
                expanded += 1
                if node == goal or (stop_time is not None and run.t[sid] >= stop_time):
                    return run.reconstruct(sid), expanded, "ok"
                for child in run.children(sid, AT, f):
                    push(child)
        if goal is not None and t_last < t_start + cfg.max_plan_s and not expanded:
            if t_last < t_start:
                return None, expanded, "goal blocked by the person for good"
            return None, expanded, f"goal blocked by the person from t={t_last - t_start:+.2f} s on"
        what = "goal" if goal is not None else "the emergency horizon"
        return None, expanded, f"{what} unreachable: no safe path found after {expanded} expansions"

    def _latest_goal_arrival(self, sep: _Separation, goal: int, t_start: float, hold_s: float) -> float:
        """The latest arrival at the goal from which the robot could stand there for ``hold_s``, when the
        forecast person blocks every goal branch for good after some time (their last pose is held and the
        margin stops growing at its cap); +inf when some branch stays free or without a forecast."""
        fc = sep.forecast
        if fc is None:
            return math.inf
        cfg = self.config
        m_end = float(fc.margins[-1])
        cap = max(fc.max_margin_m, float(fc.margins.max()))
        t_sat = fc.horizon_end + (max(cap - m_end, 0.0) / fc.growth_mps if fc.growth_mps > 0 else 0.0)
        t_sat = max(t_sat, t_start) + hold_s
        n = max(math.ceil((t_sat - t_start) / cfg.sample_dt_s), 1)
        ts = t_start + (t_sat - t_start) * np.arange(n + 1) / n
        branches = np.flatnonzero(self._valid[goal])
        nb = branches.size
        rep = np.repeat(branches, n + 1)
        ok = sep.check(
            self._ik[goal, rep],
            np.tile(ts, nb),
            np.zeros(rep.size),
            self._cen_all[goal, rep],
            self._rad_all[goal, rep],
        ).reshape(nb, n + 1)
        if np.any(ok[:, -1]):
            return math.inf
        k_hold = math.ceil(hold_s / ((t_sat - t_start) / n) - 1e-9)
        best = -math.inf
        for row in ok:
            # latest i with row[i .. i + k_hold] all safe
            run = 0
            for i in range(n, -1, -1):
                run = run + 1 if row[i] else 0
                if run >= k_hold + 1:
                    best = max(best, float(ts[i]))
                    break
        return best

    def _moves_ok(
        self,
        sep: _Separation,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cen_a: np.ndarray,
        rad_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        t_dep: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        peak: np.ndarray,
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
    ) -> np.ndarray:
        """Check moves (and the hold at their end where ``hold``) against the forecast; boolean (M,).

        Per move: the start configuration ``q_a`` with its capsule points/spheres, the target roadmap node
        ``cv`` at branch ``b`` (configuration ``target``), departure, duration, entry speed, length, whether
        it ends at rest, its peak path speed and its cruise speed ``f``.
        """
        M = q_a.shape[0]
        if sep.forecast is None or M == 0:
            return np.ones(M, dtype=bool)
        cfg = self.config
        dq = target - q_a
        cum = np.concatenate([np.zeros((M, 1)), np.cumsum(np.abs(dq) * self._lever, axis=1)], axis=1)
        travel = cum[:, self._moved_by]  # (M, L): how far joints 1..J(l) can carry capsule l
        cen_b, rad_b = self._cen_all[cv, b], self._rad_all[cv, b]
        # robot speed for S_r + S_s: the largest chord speed of the capsule points, average -> peak, x factor
        chord = np.max(np.linalg.norm(self._pts_all[cv, b] - pts_a, axis=-1), axis=-1)
        Ls = np.maximum(L, 1e-12)
        ratio = np.where(L > 1e-12, np.maximum(peak * h / Ls, 1.0), 1.0)
        v_move = np.where(h > 0, chord / np.maximum(h, 1e-12) * ratio, 0.0) * cfg.speed_factor
        # stage 0: moves far from the person over their whole time window pass without samples; a capsule
        # point is within frac * T of its start and (1 - frac) * T of its end, so within
        # T / 2 + (rho_a + rho_b) / 2 of the middle of the two sphere centres
        near = sep.near_moves(
            0.5 * (cen_a + cen_b),
            0.5 * (rad_a + rad_b + travel),
            t_dep,
            t_dep + h + np.where(hold, hold_s, 0.0),
            v_move,
        )
        result = np.ones(M, dtype=bool)
        if not near.any():
            return result
        sel = np.flatnonzero(near)
        (
            q_a,
            pts_a,
            cen_a,
            rad_a,
            cv,
            b,
            target,
            t_dep,
            h,
            u0,
            L,
            end_rest,
            peak,
            f,
            hold,
            dq,
            travel,
            cen_b,
            rad_b,
            v_move,
        ) = (
            x[sel]
            for x in (
                q_a,
                pts_a,
                cen_a,
                rad_a,
                cv,
                b,
                target,
                t_dep,
                h,
                u0,
                L,
                end_rest,
                peak,
                f,
                hold,
                dq,
                travel,
                cen_b,
                rad_b,
                v_move,
            )
        )
        M = sel.size
        # samples: the move every sample_dt_s (its end included), then the hold
        n = np.maximum(np.ceil(h / cfg.sample_dt_s - 1e-9), 1).astype(np.int64)
        n_hold_1 = max(math.ceil(hold_s / cfg.sample_dt_s - 1e-9), 0)
        n_hold = np.where(hold, n_hold_1, 0)
        tot = n + n_hold
        owner = np.repeat(np.arange(M), tot)
        i = np.arange(owner.shape[0]) - np.repeat(np.cumsum(tot) - tot, tot) + 1
        n_o, h_o = n[owner], h[owner]
        in_move = i <= n_o
        tau = np.where(in_move, i / n_o * h_o, h_o)
        frac = np.empty(owner.shape[0])
        for fv in np.unique(f).tolist():
            grp = f[owner] == fv
            frac[grp] = _profile_fraction(
                tau[grp], u0[owner][grp], L[owner][grp], h_o[grp], fv, self._A, end_rest[owner][grp]
            )
        frac = np.where(in_move, frac, 1.0)
        q = q_a[owner] + frac[:, None] * dq[owner]
        t = t_dep[owner] + tau + np.where(in_move, 0.0, (i - n_o) * (hold_s / max(n_hold_1, 1)))
        v = np.where(in_move, v_move[owner], 0.0)
        # capsule l lies within its start sphere grown by frac * T_l and its end sphere grown by
        # (1 - frac) * T_l; take the smaller sphere
        fo = frac[:, None]
        ra = rad_a[owner] + fo * travel[owner]
        rb = rad_b[owner] + (1.0 - fo) * travel[owner]
        use_a = ra <= rb
        cen = np.where(use_a[..., None], cen_a[owner], cen_b[owner])
        rad = np.where(use_a, ra, rb)
        ok_s = sep.check(q, t, v, cen, rad)
        result[sel] = np.bincount(owner, weights=~ok_s, minlength=M) == 0
        return result


class _Run:
    """The records of one search: unchecked and checked states, in plain lists and growable arrays.

    Owned by one query (never shared, never written to the roadmap). A state is a move from a parent state
    to a roadmap node at an IK branch: departure, duration, entry/exit path speed, cruise speed, and the
    alternative it is (0 = nearest branch at cruise speed; others are pushed when it fails).
    """

    def __init__(
        self,
        planner: Planner,
        q_start: np.ndarray,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        stop_time: float | None,
        hold_s: float,
    ) -> None:
        self.p = planner
        self.sep = sep
        self.goal = goal
        self.stop_time = stop_time
        self.hold_s = hold_s
        cfg = planner.config
        self.f = cfg.speed_fraction
        self.A = planner._A
        self.min_edge = cfg.min_edge_s
        # per state (lists)
        self.node: list[int] = [-1]
        self.branch: list[int] = [-1]
        self.t: list[float] = [t_start]
        self.u: list[float] = [0.0]
        self.parent: list[int] = [-1]
        self.dep: list[float] = [t_start]
        self.fc: list[float] = [self.f]
        self.L: list[float] = [0.0]
        self.h: list[float] = [0.0]
        self.end: list[bool] = [False]
        self.peak: list[float] = [0.0]
        self.same: list[bool] = [True]
        self.alt: list[int] = [0]
        self.opts: list[list[tuple[int, float, bool]] | None] = [None]
        # per checked state: configuration, capsule points and spheres (start: computed here)
        pts, cen, rad = planner._points_and_spheres(q_start[None])
        self.q = np.empty((64, 6))
        self.q[0] = q_start
        self.checked_q = np.zeros(64, dtype=bool)
        self.checked_q[0] = True
        self.start_pts, self.start_cen, self.start_rad = pts[0], cen[0], rad[0]
        self.wait_safe_until: dict[int, float] = {}

    # -- records
    def _new(
        self,
        node: int,
        branch: int,
        t: float,
        u: float,
        parent: int,
        dep: float,
        fc: float,
        L: float,
        h: float,
        end: bool,
        peak: float,
        same: bool,
        alt: int,
        opts: list[tuple[int, float, bool]] | None,
    ) -> int:
        self.node.append(node)
        self.branch.append(branch)
        self.t.append(t)
        self.u.append(u)
        self.parent.append(parent)
        self.dep.append(dep)
        self.fc.append(fc)
        self.L.append(L)
        self.h.append(h)
        self.end.append(end)
        self.peak.append(peak)
        self.same.append(same)
        self.alt.append(alt)
        self.opts.append(opts)
        sid = len(self.node) - 1
        if sid >= self.q.shape[0]:
            grow = self.q.shape[0] * 2
            self.q = np.concatenate([self.q, np.empty((grow, 6))])
            self.checked_q = np.concatenate([self.checked_q, np.zeros(grow, dtype=bool)])
        return sid

    def _move(
        self,
        parent: int,
        node: int,
        opt: tuple[int, float, bool],
        t_dep: float,
        u0: float,
        fc: float,
        alt: int,
        opts: list[tuple[int, float, bool]] | None,
        AT: list[float],
    ) -> int | None:
        branch, L, same = opt
        end = node == self.goal
        h, u1, peak = _profile_py(u0, L, fc, self.A, end)
        if L > 1e-12:
            h = max(h, self.min_edge)
        ta = t_dep + h
        if ta >= AT[node] - _EPS_T:
            return None
        return self._new(node, branch, ta, u1, parent, t_dep, fc, L, h, end, peak, same, alt, opts)

    # -- generation (plain Python)
    def start_options(self) -> list[int]:
        """Unchecked moves from the start to its nearest roadmap nodes (all checked against the scene)."""
        p = self.p
        q = self.q[0]
        aligned = p._align(p._ik, q[None, None, :])
        L = np.where(p._valid, p._metric(aligned - q), np.inf)
        best = L.min(axis=1)
        k = min(p.config.start_neighbors, int(np.isfinite(best).sum()))
        if k == 0:
            return []
        nodes = np.argpartition(best, k - 1)[:k]
        order = np.argsort(L[nodes], axis=1, kind="stable")[:, : p._R]
        Lo = np.take_along_axis(L[nodes], order, axis=1)
        AT = [math.inf] * p.roadmap.num_nodes
        out = []
        for v, bs, ls in zip(nodes.tolist(), order.tolist(), Lo.tolist(), strict=True):
            opts = [(b, ln, False) for b, ln in zip(bs, ls, strict=True) if ln < math.inf]
            if opts:
                sid = self._move(0, v, opts[0], self.t[0], 0.0, self.f, 0, opts, AT)
                if sid is not None:
                    out.append(sid)
        return out

    def children(self, sid: int, AT: list[float], f: float) -> list[int]:
        """Unchecked moves from a checked state to its roadmap neighbours (nearest branch, cruise speed)."""
        out = []
        t, u = self.t[sid], self.u[sid]
        for v, opts in self.p._succ(self.node[sid], self.branch[sid]):
            child = self._move(sid, v, opts[0], t, u, f, 0, opts, AT)
            if child is not None:
                out.append(child)
        return out

    def alternatives(self, sid: int, AT: list[float]) -> list[int]:
        """When the nearest branch at cruise speed fails: the next branches, slower, and after a wait."""
        if self.alt[sid] != 0 or self.opts[sid] is None:
            return []
        cfg = self.p.config
        par, node, opts = self.parent[sid], self.node[sid], self.opts[sid]
        t, u = self.t[par], self.u[par]
        out = []
        for opt in opts[1:]:
            out.append(self._move(par, node, opt, t, u, self.f, 1, None, AT))
        if self.sep.forecast is not None:
            for fs in cfg.slow_speed_fractions:
                if fs < self.f:
                    out.append(self._move(par, node, opts[0], t, min(u, fs), fs, 2, None, AT))
            K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
            for k in range(1, K + 1):
                out.append(self._move(par, node, opts[0], t + k * cfg.wait_step_s, 0.0, self.f, 3, None, AT))
        return [s for s in out if s is not None]

    # -- checking (vectorised)
    def check(self, batch: list[int]) -> list[bool]:
        """Check a batch of unchecked moves; stores the configuration of every move that passes."""
        p = self.p
        idx = np.array(batch, dtype=np.int64)
        par = np.array([self.parent[s] for s in batch], dtype=np.int64)
        cv = np.array([self.node[s] for s in batch], dtype=np.int64)
        b = np.array([self.branch[s] for s in batch], dtype=np.int64)
        q_par = self.q[par]
        target = p._align(p._ik[cv, b], q_par)
        M = idx.size
        ok = np.ones(M, dtype=bool)
        # static scene: moves the roadmap checked (same branch, edge bit, the same move) need nothing more
        same = np.array([self.same[s] for s in batch], dtype=bool)
        pn = np.array([self.node[s] for s in par.tolist()], dtype=np.int64)
        pb = np.array([self.branch[s] for s in par.tolist()], dtype=np.int64)
        chk = np.flatnonzero(same & (pn >= 0))
        if chk.size:
            ref = p._ik[pn[chk], pb[chk]]
            ref_t = p._align(p._ik[cv[chk], b[chk]], ref)
            moved = np.abs((ref_t - ref) - (target[chk] - q_par[chk])).max(axis=1) > 1e-9
            same[chk[moved]] = False
        todo = np.flatnonzero(~same)
        if todo.size:
            ok[todo] = p._static_cached(pn[todo], pb[todo], cv[todo], b[todo], q_par[todo], target[todo]) == 1
        if self.sep.forecast is not None:
            live = np.flatnonzero(ok)
            if live.size:
                ok[live] = self._check_forecast(
                    idx[live], par[live], cv[live], b[live], q_par[live], target[live]
                )
        good = idx[ok]
        self.q[good] = target[ok]
        self.checked_q[good] = True
        return ok.tolist()

    def _parent_geometry(self, par: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = self.p
        pn = np.array([self.node[s] for s in par.tolist()], dtype=np.int64)
        pb = np.array([self.branch[s] for s in par.tolist()], dtype=np.int64)
        on = pn >= 0
        pts = np.where(on[:, None, None], p._pts_all[pn.clip(0), pb.clip(0)], self.start_pts[None])
        cen = np.where(on[:, None, None], p._cen_all[pn.clip(0), pb.clip(0)], self.start_cen[None])
        rad = np.where(on[:, None], p._rad_all[pn.clip(0), pb.clip(0)], self.start_rad[None])
        return pts, cen, rad

    def _check_forecast(
        self,
        idx: np.ndarray,
        par: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        q_par: np.ndarray,
        target: np.ndarray,
    ) -> np.ndarray:
        p = self.p
        cfg = p.config
        ok = np.ones(idx.size, dtype=bool)
        pts, cen, rad = self._parent_geometry(par)
        # waits: the parent must be able to stand still until the departure
        dep = np.array([self.dep[s] for s in idx.tolist()])
        t_par = np.array([self.t[s] for s in par.tolist()])
        waiting = np.flatnonzero(dep > t_par + _EPS_T)
        if waiting.size:
            todo = sorted({int(par[i]) for i in waiting.tolist()} - set(self.wait_safe_until))
            if todo:
                K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
                sub = max(1, math.ceil(cfg.wait_step_s / cfg.sample_dt_s - 1e-9))
                n = K * sub
                tp = np.array(todo, dtype=np.int64)
                ts = np.array([self.t[s] for s in todo])[:, None] + (cfg.wait_step_s / sub) * np.arange(
                    1, n + 1
                )
                rep = np.repeat(np.arange(tp.size), n)
                pg = self._parent_geometry(tp)
                res = self.sep.check(
                    self.q[tp][rep], ts.reshape(-1), np.zeros(rep.size), pg[1][rep], pg[2][rep]
                )
                res = res.reshape(tp.size, n)
                for j, s in enumerate(todo):
                    bad = np.flatnonzero(~res[j])
                    self.wait_safe_until[s] = float(ts[j, bad[0]]) if bad.size else math.inf
            safe = np.array([self.wait_safe_until[int(par[i])] for i in waiting.tolist()])
            ok[waiting] = dep[waiting] < safe - _EPS_T
        live = np.flatnonzero(ok)
        if live.size == 0:
            return ok
        sl = idx[live]
        get = lambda arr: np.array([arr[s] for s in sl.tolist()])  # noqa: E731
        hold = cv[live] == self.goal if self.goal is not None else np.full(live.size, self.hold_s > 0)
        ok[live] = p._moves_ok(
            self.sep,
            q_par[live],
            pts[live],
            cen[live],
            rad[live],
            cv[live],
            b[live],
            target[live],
            dep[live],
            get(self.h),
            np.array(self._u0(sl)),
            get(self.L),
            get(self.end).astype(bool),
            get(self.peak),
            get(self.fc),
            hold,
            self.hold_s,
        )
        return ok

    def _u0(self, sids: np.ndarray) -> list[float]:
        """Entry path speed of each move (0 after a wait, the parent's exit speed capped at the cruise)."""
        out = []
        for s in sids.tolist():
            if self.alt[s] == 3:
                out.append(0.0)
            else:
                out.append(min(self.u[self.parent[s]], self.fc[s]))
        return out

    def reconstruct(self, sid: int) -> Plan:
        chain = []
        s = sid
        while s >= 0:
            chain.append(s)
            s = self.parent[s]
        chain.reverse()
        if len(chain) > 1:
            a, c = chain[0], chain[1]
            if self.t[c] <= self.t[a] + _EPS_T and np.allclose(self.q[a], self.q[c], atol=1e-12):
                chain = chain[1:]  # the start is a roadmap node: one waypoint, labelled with the node
        times, qs, nodes = [], [], []
        for i, s in enumerate(chain):
            if i > 0:
                par = chain[i - 1]
                if self.dep[s] > self.t[par] + _EPS_T:  # waited at the parent
                    times.append(self.dep[s])
                    qs.append(self.q[par])
                    nodes.append(self.node[par])
            times.append(self.t[s])
            qs.append(self.q[s])
            nodes.append(self.node[s])
        return Plan(times=np.array(times), q=np.array(qs), nodes=np.array(nodes))


def _profile_py(u0: float, L: float, f: float, A: float, end_rest: bool) -> tuple[float, float, float]:
    """:func:`_profile` for one move, in plain Python (the same formulas)."""
    u0 = min(u0, f)
    u0sq = u0 * u0
    if not end_rest:
        u1 = min(math.sqrt(u0sq + 2.0 * A * L), f)
        return (u1 - u0) / A + max(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f, u1, u1
    up = min(f, math.sqrt((2.0 * A * L + u0sq) / 2.0))
    if u0sq <= 2.0 * A * L:
        cruise = max(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
        return (up - u0) / A + cruise / max(up, 1e-12) + up / A, 0.0, up
    return 2.0 * L / max(u0, 1e-12), 0.0, u0


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
