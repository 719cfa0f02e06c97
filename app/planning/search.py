"""Time-variant A* over the static roadmap (sequential and batched-parallel), emergency plans, validity check.

Paper, section II-A, and where this goes further:

- **State.** Per roadmap node ``v`` the search keeps the arrival time ``AT(v)``; every state is a record of
  the search (node, IK branch, time, path speed, parent, departure, and its configuration ``Cfg(v)`` once
  checked), one row of the query's own growable arrays, so a plan is rebuilt from exactly the configurations
  and times that were checked. The roadmap is never written to.
- **Expansion u -> v.** The IK branches of ``v`` (each shifted by multiples of 2 pi next to ``Cfg(u)``) are
  ordered by the time a straight joint move needs (precomputed per edge and branch); the nearest is tried
  first, the others (at most ``max_branch_tries``) when it fails. A move between the same branch at both ends
  uses the roadmap's static edge check; any other move (another branch, the start connection) is checked
  against the static scene on the fly (memoised). Successors of a whole batch of states are generated and
  timed in one vectorised pass.
- **Heuristic.** The static time-to-go over the search's own moves at the cruise speed: a backward Dijkstra
  from the goal's branches over the precomputed move table (once per goal, cached), never above the time of
  any path the search can return (its moves last at least their length over the cruise speed). Without a
  person the search then expands little more than the optimal path; with one, the time-variant search stays
  close to the static one where the person is not in the way.
- **Lazy checking.** Successors are pushed *unchecked*; a move is checked only when its state is popped (its
  key ``t + h`` is a lower bound of any checked path through it, so the order is still A*'s).
- **Edge timing.** The paper lets every edge last as long as the slowest joint needs at its velocity limit.
  With the UR5e's acceleration limits that is too optimistic near starts and stops, and a trajectory fitted to
  it would run late: the forecast person would then be checked at the wrong time. Here the path speed (the
  largest joint speed as a fraction of its limit) follows a 1-D profile: it accelerates with the smallest
  joint acceleration/velocity ratio up to the cruise speed and brakes to rest on the edge into the goal
  (and moves from rest after a wait or a stop).
- **Validity against the forecast.** A move is valid if at every sampled instant (every ``sample_dt_s`` and
  at its end) the surface distance robot-person is at least :func:`app.safety.ssm.forecast_clearance`
  for the robot's speed there and the forecast's margin at that instant (``S_r + S_s + C + Z_r +
  max(Z_d, margin)``; the margin grows with the horizon; beyond the horizon the last pose is held and the
  margin grows at ``growth_mps`` up to a cap) plus ``corridor_margin_m`` (room for the fitted spline's
  deviation from the straight moves). The robot's speed at a sample is the largest the path profile reaches
  since the previous sample, in m/s through the move's largest chord (x ``speed_factor``), so a robot that
  brakes into a station needs less room there than at its peak speed. The forecast takes the place of
  ISO/TS 15066's worst-case ``S_h = v_h (T_r + T_s)`` over the planning horizon; the supervisor applies the
  full ``S_p`` to the current pose on top (speed scaling), so both views hold at run time.
- **Slower, then waiting (safe-interval style).** When the nearest branch fails at the cruise speed, the
  next branches are tried, the nearest one at ``slow_speed_fractions`` (less ``S_r + S_s``; the slowest, a
  creep, also after stopping), and after waiting at ``u`` in steps of ``wait_step_s`` up to ``max_wait_s``
  (if standing still there is itself safe). Once the person holds still (last pose, margin at its cap)
  waiting longer changes nothing, so of the waits that depart then only the first is tried. Without a person
  the search is plain A*.
- **Pruning and early failure.** When the person blocks every goal branch for good after some time, states
  that cannot arrive before it (by the heuristic) are not pushed; a goal blocked from the start fails at
  once. After ``probe_after_expansions`` the search asks whether the goal can still be *entered* once the
  person holds still (:meth:`Planner._approach_probe`); when not, states that could only get there later are
  dropped and the search ends soon with that reason instead of exhausting the roadmap. Plans longer than
  ``max_plan_s`` are not searched for.
- **Parallel.** ``workers = N`` checks up to N moves per step in one vectorised call (the batched
  equivalent of the paper's N threads taking nodes from the open list in turn; in CPython threads would
  serialise on the interpreter lock): the best popped state takes a *lookahead* chain of moves along the
  static shortest path (shorter where such chains keep failing), the other slots go to the next states in
  key order. A chain's states are ordinary states: each is accepted only when popped in key order after its
  parent was. ``AT`` is updated only when a checked arrival improves it and a goal state is accepted only
  when nothing pending can beat it, so the validity guarantees and the result are those of the sequential
  search (up to ties); a node may be expanded again when a later batch improves it.
- **Broad phase.** Whole moves far from the person over their time window, then single samples, are passed
  without forward kinematics (bounding spheres of the robot capsules grown by how far the joints can carry
  them, against a box around the person); the exact distance runs only over the robot and person capsules
  that come near each other, and a sample certainly too close (an upper bound of the distance, from points on
  the capsule axes) fails its move without exact distances for the move's other samples. With the compiled
  UR5e capsule model (:meth:`CollisionModel.kernel_geometry`) the move, sample and trajectory checks run
  fused in :mod:`app.planning._kernels` (the same broad phase and distances; a move stops at its first
  failing sample, a verification at its first failing instant); the NumPy checks are their reference.
- **Compiled bookkeeping.** With the compiled model the search's own bookkeeping runs in
  :mod:`app.planning._kernels` too: successor generation and timing (children, alternatives, the lookahead
  chain) writing straight into the packed state records, the open list (a binary heap of entry indices that
  pops in exactly ``heapq``'s order over the ``(key, -t, id)`` tuples) with the pop loop up to each step that
  needs Python, the batch's check set-up, the wait samples and the acceptance after a check. The NumPy and
  ``heapq`` code is its reference (used with a NumPy model): both expand the same states in the same order
  and return the same waypoints, bit for bit.
- **Shortcuts.** Roadmap paths follow straight TCP segments between samples, so in joint space they
  zig-zag and a spline through them slows down at every reversal. Before the fit, runs of waypoints are
  replaced greedily by one straight joint move where that move is statically free and keeps the forecast
  clearance over time (the search's own move check, timed by the same path-speed profile); the shortened
  path is re-timed, and the search's waypoints stay where no shortcut passes (:meth:`Planner._shortcut`).
  Waits and everything before the last of them are kept as the search timed them. The shortened plan is
  fitted and verified like any plan below; when it fails, the search's own path is fitted instead.
- **Trajectory check.** The waypoints become a C1 spline (:class:`app.planning.trajectory.Trajectory`),
  possibly retimed to the acceleration limits; it is verified against the forecast at ``verify_dt_s``
  with :meth:`Planner.first_violation` (and against the static scene). If the spline fails, a trajectory at
  rest at every waypoint (the straight moves the search checked, slower) is verified instead; if that fails,
  the search is repeated once with a time-robust check (each robot sample against the person over
  ``[t, t + slack]``); if that fails too, the result is a failure. A returned plan carries the verified knots
  (``Plan.qd``).
- **Emergency plan.** The person is held at the current pose; the robot stays put if that is safe for the
  horizon, else the search stops as soon as a state reaches ``t_start + horizon_s`` (paper: ``F + D``).
"""

from __future__ import annotations

import heapq
import inspect
import itertools
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from app.planning import _kernels
from app.planning.roadmap import NUM_BRANCHES, Roadmap
from app.planning.ssm_timing import PredictedTiming
from app.planning.trajectory import Plan, Trajectory, TrajectoryError, fit_knots
from app.prediction.skeleton import NUM_JOINTS
from app.safety.governor import GovernorModel
from app.safety.ssm import SSMParams, forecast_clearance

if TYPE_CHECKING:
    from scipy.sparse import csr_matrix

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

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray: ...


#: Slower timings of a path tried when its fitted trajectory fails verification (durations x factor).
_STRETCH_FACTORS = (1.5, 2.5)


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
            The search's check is a filter: every returned trajectory is verified every ``verify_dt_s``.
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
            The slowest (0.08: a creep, about 0.25 rad/s per joint) lets the robot approach a station next
            to a hand that rests there, the way speed and separation monitoring would slow it at run time.
        goal_hold_s: After arriving at the goal the robot must be able to stand there this long (s).
        ssm_aware_search: With the governor's model (``Planner.plan(timing=...)``), a move also needs the
            separation that the governor needs to let it run at its speed
            (:meth:`app.safety.governor.GovernorModel.extra_clearance`), beyond that of a creep: near the
            person the search takes moves slower or goes round, and the arrival times it optimises are
            those the robot will reach. Off by default: in the shipped cell the drop stations lie inside the
            governor's creep zone of the working person, the search then finds no plan for long spells,
            and on the tuning seeds 1000-1003 (120 s) the robot waited 77-97 s per trial for a plan and
            completed fewer tasks (0.25 and 0 against 0.5 per method).
        ssm_creep_mps: The part speed (m/s) up to which a move needs no more than today's clearance: the
            speed at which the governor lets a robot creep past a person at work.
        ssm_brake_decel_mps2: The deceleration (m/s^2) of a braking robot's fastest point for that table:
            the governor brakes at 3 rad/s^2 per joint, about 1.5 m/s^2 at the 0.5 m from the moving joints
            to the fastest point of a typical move of this cell.
        start_neighbors: Number of roadmap nodes the start configuration is connected to.
        check_step_rad: Largest joint step (rad) between configurations checked against the static scene.
        static_margin_m: Clearance (m) from the static scene for on-the-fly checks (as the roadmap's).
        max_expansions: Bound on expanded states per search.
        probe_after_expansions: After this many expansions without a plan the search checks whether the
            goal can still be entered once the forecast person holds still (:meth:`Planner._approach_probe`);
            when it cannot, states that could only arrive later are dropped (a clear, early failure).
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
        shortcut: Shorten the found path before the trajectory is fitted (:meth:`Planner._shortcut`):
            runs of waypoints become one straight joint move where that move is statically free and keeps
            the forecast clearance; the result is verified like any plan, the unshortened path is the
            fallback.
        shortcut_rounds: Bound on the vectorised checks of shortcut candidates (each checks every shortcut
            from one waypoint); one more call then checks the move straight to the goal and the rest of the
            search's waypoints, re-timed.
    """

    ssm: SSMParams = field(default_factory=SSMParams)
    speed_fraction: float = 0.5
    accel_fraction: float = 0.8
    min_edge_s: float = 0.02
    sample_dt_s: float = 0.08
    corridor_margin_m: float = 0.02
    speed_factor: float = 1.3
    wait_step_s: float = 0.1
    max_wait_s: float = 0.6
    max_branch_tries: int = 2
    heuristic_weight: float = 1.0
    slow_speed_fractions: tuple[float, ...] = (0.2, 0.08)
    ssm_aware_search: bool = False
    ssm_creep_mps: float = 0.15
    ssm_brake_decel_mps2: float = 1.5
    goal_hold_s: float = 0.3
    start_neighbors: int = 8
    check_step_rad: float = 0.05
    static_margin_m: float = 0.0
    max_expansions: int = 20000
    probe_after_expansions: int = 80
    max_plan_s: float = 8.0
    verify_dt_s: float = 0.01
    fallback_slack_s: float = 0.3
    emergency_hold_s: float = 0.3
    lever_arm_m: float = 1.3
    q_min: tuple[float, ...] | None = None
    q_max: tuple[float, ...] | None = None
    qd_max: tuple[float, ...] | None = None
    qdd_max: tuple[float, ...] | None = None
    shortcut: bool = True
    shortcut_rounds: int = 3

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.speed_fraction must be in (0, 1], got {self.speed_fraction}")
        if not 0.0 < self.accel_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.accel_fraction must be in (0, 1], got {self.accel_fraction}")
        for name in ("sample_dt_s", "verify_dt_s", "check_step_rad", "wait_step_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.shortcut_rounds < 1:
            raise ValueError(f"PlannerConfig.shortcut_rounds must be >= 1, got {self.shortcut_rounds}")
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
        arrival_s: When the robot is predicted to arrive (s, runtime clock): with ``Planner.plan(timing=...)``
            under the speed governor (the timing the plan was verified at), else the trajectory's end.
    """

    ok: bool
    plan: Plan | None
    reason: str
    expanded: int
    compute_s: float
    trajectory: Trajectory | None = None
    arrival_s: float | None = None


def _profile_samples(
    s: np.ndarray,
    s_prev: np.ndarray,
    u0: np.ndarray,
    L: np.ndarray,
    dur: np.ndarray,
    f: np.ndarray,
    A: float,
    end_rest: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Path fraction (0..1) covered at profile time ``s`` and the largest path speed over ``[s_prev, s]``
    (fraction of full speed) of moves timed by :func:`_profile_arrays` (one entry per sample, ``u0 <= f``).

    The profile accelerates at ``A`` from ``u0`` to the cruise speed ``f``; a move that ends at rest brakes
    at ``A`` to stop at ``dur`` (or, when it cannot, uniformly from ``u0``). Its path speed is unimodal, so
    the largest speed over an interval is the speed at the interval's point nearest the peak.
    """
    t1 = (f - u0) / A  # end of the acceleration toward the cruise speed
    pos = np.where(s <= t1, (u0 + 0.5 * A * s) * s, (u0 + 0.5 * A * t1) * t1 + f * (s - t1))
    speed = np.minimum(u0 + A * s, f)  # increasing: the largest at the interval's end
    if end_rest.any():
        up = np.minimum(f, np.sqrt((2.0 * A * L + u0 * u0) / 2.0))
        can = u0 * u0 <= 2.0 * A * L
        ta = (up - u0) / A
        rem = dur - s
        p_rest = np.where(
            s <= ta,
            (u0 + 0.5 * A * s) * s,
            np.where(rem <= up / A, L - 0.5 * A * rem * rem, (u0 + 0.5 * A * ta) * ta + up * (s - ta)),
        )
        a_forced = u0 / np.maximum(dur, 1e-12)
        p_forced = u0 * s - 0.5 * a_forced * s * s
        # speed: up (plateau or apex) from ta on, braking over the last up / A seconds
        sp = np.minimum(np.minimum(u0 + A * np.minimum(s, ta), up), A * (dur - s_prev))
        sp_forced = np.maximum(u0 - a_forced * s_prev, 0.0)  # decreasing: largest at the start
        pos = np.where(end_rest, np.where(can, p_rest, p_forced), pos)
        speed = np.where(end_rest, np.where(can, sp, sp_forced), speed)
    frac = np.where(L > 1e-12, pos / np.maximum(L, 1e-12), 1.0)
    return np.minimum(np.maximum(frac, 0.0), 1.0), speed


def _paired_options(model: RobotModel) -> set[str]:
    """The keyword options of ``model.distance_to_human_paired`` (``segments``, ``links``, ``capsules``)."""
    try:
        params = inspect.signature(model.distance_to_human_paired).parameters
    except (TypeError, ValueError):
        return set()
    return {name for name in ("segments", "links", "capsules") if name in params}


class _Separation:
    """Pass/fail of robot samples (and whole moves) against a forecast person.

    Two stages, the first conservative: (0/1) a sphere per robot capsule (for a whole move one that contains
    the capsule during the move, see :meth:`Planner._moves_ok`; for a sample one known without forward
    kinematics) against a box that contains the whole person over the time window; (2) for the samples still
    close, the exact minimum surface distance robot-person
    (:meth:`app.planning.collision.CollisionModel.distance_to_human_paired`) against the pose interpolated
    at the sample's time. The boxes are precomputed once per query at the forecast's own samples (a pose
    between two samples is a blend of them, so it lies in the union of their boxes; beyond the horizon the
    last pose is held), with a sparse table for unions over longer windows.
    """

    def __init__(
        self,
        model: RobotModel,
        forecast: HumanForecast | None,
        ssm: SSMParams,
        *,
        extra_m: float,
        offsets: tuple[float, ...] = (0.0,),
        floor_m: float | None = None,
        subsets: bool = False,
        cap_ends: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        robot_r: np.ndarray | None = None,
        kernel: tuple[object, ...] | None = None,
        ssm_extra: tuple[float, np.ndarray] | None = None,
    ) -> None:
        self.model = model
        self.forecast = forecast
        self.ssm = ssm
        self.extra_m = extra_m
        #: SSM-aware search: ``(dv, extra)``, the governor's extra clearance (m) at speeds ``i * dv``
        #: (:meth:`app.safety.governor.GovernorModel.extra_clearance`), or None.
        self.ssm_extra = ssm_extra
        self.offsets = offsets
        self.floor_m = floor_m
        self.samples = 0
        self.exact_samples = 0
        self.t_static = math.inf  # from then on the person holds still and the margin is constant (s)
        self._kernel = None
        if forecast is None:
            return
        m_end = float(forecast.margins[-1])
        cap = max(forecast.max_margin_m, float(forecast.margins.max()))
        grow = max(cap - m_end, 0.0) / forecast.growth_mps if forecast.growth_mps > 0 else 0.0
        self.t_static = forecast.horizon_end + grow - min(offsets)
        joints = forecast.joints  # (H, J, 3)
        r_max = float(np.max(model.human_capsules(joints[:1])[2]))
        lo = joints.min(axis=1) - r_max  # (H, 3): every capsule of the pose lies inside
        # the margin rides along as a 4th column of the upper table (unions take its maximum)
        hi = np.concatenate([joints.max(axis=1) + r_max, forecast.margins[:, None]], axis=1)
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
        self._H = forecast.times.shape[0]
        self._joints = joints
        self._djoints = np.diff(joints, axis=0)
        self._dtimes = np.diff(forecast.times)
        self._margin_arr = forecast.margins
        self._cap = max(forecast.max_margin_m, float(forecast.margins.max()))
        # boxes around two consecutive samples (a sample's own box when there is only one)
        self._lo_pair = self._lo_tab[1] if len(self._lo_tab) > 1 else lo
        self._hi_pair = self._hi_tab[1] if len(self._hi_tab) > 1 else hi
        self._n_pair = self._lo_pair.shape[0]
        # the compiled check (``kernel``: CollisionModel.kernel_geometry()) and its forecast arrays
        self._kernel = kernel
        if kernel is not None:
            H, J = joints.shape[0], joints.shape[1]
            self._k_forecast = (
                _kernels.as_f64(self._times),
                _kernels.as_f64(joints),
                _kernels.as_f64(self._djoints if H > 1 else np.zeros((1, J, 3))),
                _kernels.as_f64(self._dtimes if H > 1 else np.ones(1)),
                _kernels.as_f64(self._lo_pair),
                _kernels.as_f64(self._hi_pair),
            )
            # the sparse table as (levels, H, .) arrays (level k is valid on its first H - 2^k + 1 rows)
            n_lev = len(self._lo_tab)
            lo_tab, hi_tab = np.zeros((n_lev, H, 3)), np.zeros((n_lev, H, 4))
            for k, (a, b) in enumerate(zip(self._lo_tab, self._hi_tab, strict=True)):
                lo_tab[k, : a.shape[0]] = a
                hi_tab[k, : b.shape[0]] = b
            self._k_window = (_kernels.as_f64(self._margin_arr), lo_tab, hi_tab)
            self._k_params = np.array(
                [
                    forecast.growth_mps,
                    self._cap,
                    ssm.robot_time_s,
                    ssm.intrusion_m,
                    ssm.z_robot_m,
                    ssm.z_human_m,
                    extra_m,
                    math.inf if floor_m is None else floor_m,
                    *(() if ssm_extra is None else (ssm_extra[0], *np.asarray(ssm_extra[1]).tolist())),
                ],
                dtype=np.float64,
            )
            self._k_offsets = np.array(offsets, dtype=np.float64)
        # per person capsule boxes (for the exact stage to skip capsules far from the robot), sparse table
        # the exact stage's shortcuts need the collision model's segments and capsule subsets
        self._subsets = subsets and cap_ends is not None and robot_r is not None
        if self._subsets:
            assert cap_ends is not None and robot_r is not None
            self._cap_ends, self._robot_r = cap_ends, robot_r
        if self._subsets:
            ha, hb, hr = model.human_capsules(joints)
            clo = np.minimum(ha, hb) - np.asarray(hr)[None, :, None]  # (H, M, 3)
            chi = np.maximum(ha, hb) + np.asarray(hr)[None, :, None]
            self._clo_tab, self._chi_tab = [clo], [chi]
            k = 1
            while (1 << k) <= clo.shape[0]:
                plo, phi = self._clo_tab[-1], self._chi_tab[-1]
                half = 1 << (k - 1)
                self._clo_tab.append(np.minimum(plo[:-half], plo[half:]))
                self._chi_tab.append(np.maximum(phi[:-half], phi[half:]))
                k += 1

    def _boxes(self, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boxes that contain the person over each window [t0, t1] (t0 <= t1): lower corners (n, 3) and
        upper corners with the largest forecast margin at the samples of the window appended (n, 4)."""
        times = self._times
        H = self._H
        i0 = np.minimum(np.maximum(np.searchsorted(times, t0, side="right") - 1, 0), H - 1)
        i1 = np.maximum(np.minimum(np.searchsorted(times, t1, side="left"), H - 1), i0)
        k = np.floor(np.log2(i1 - i0 + 1)).astype(np.int64)
        lo = np.empty((t0.shape[0], 3))
        hi = np.empty((t0.shape[0], 4))
        uk = np.unique(k)
        for kk in uk.tolist():
            sel = slice(None) if uk.size == 1 else np.flatnonzero(k == kk)
            a, b = i0[sel], i1[sel] - (1 << kk) + 1
            lo[sel] = np.minimum(self._lo_tab[kk][a], self._lo_tab[kk][b])
            hi[sel] = np.maximum(self._hi_tab[kk][a], self._hi_tab[kk][b])
        return lo, hi

    def _margins(self, t: np.ndarray) -> np.ndarray:
        """The forecast's margins at times ``t`` (as :meth:`HumanForecast.poses_at`, without the poses)."""
        fc = self.forecast
        assert fc is not None
        m = np.interp(t, self._times, self._margin_arr)
        if fc.growth_mps > 0.0:
            m = np.minimum(m + fc.growth_mps * np.maximum(t - self._times[-1], 0.0), self._cap)
        return m

    def _clearance(self, v: np.ndarray, margin: np.ndarray) -> np.ndarray:
        """The separation (m) asked of the robot moving at ``v`` from a forecast pose of ``margin``."""
        req = forecast_clearance(v, margin, self.ssm) + self.extra_m
        if self.ssm_extra is not None:
            dv, table = self.ssm_extra
            grid = np.arange(table.shape[0]) * dv
            req = req + np.interp(np.maximum(v, 0.0), grid, table)
        return req if self.floor_m is None else np.minimum(req, self.floor_m)

    def _required(self, v: np.ndarray, t: np.ndarray) -> np.ndarray:
        return self._clearance(v, self._margins(t))

    def _poses(self, t: np.ndarray) -> np.ndarray:
        """Poses (n, J, 3) at times ``t`` (n,): :meth:`HumanForecast.poses_at`'s interpolation."""
        if self._H == 1:
            return np.broadcast_to(self._joints, (t.shape[0], *self._joints.shape[1:]))
        times = self._times
        tc = np.minimum(np.maximum(t, times[0]), times[-1])
        i0 = np.minimum(np.searchsorted(times, tc, side="right"), self._H - 1) - 1
        w = (tc - times[i0]) / self._dtimes[i0]
        return self._joints[i0] + w[:, None, None] * self._djoints[i0]

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
        # the largest requirement over the window: its largest margin (at a forecast sample inside it, at
        # either end, or grown beyond the horizon at its end)
        m_hi = np.maximum(hi[:, 3], np.maximum(self._margins(t0 + lo_off), self._margins(t1 + hi_off)))
        hi = hi[:, :3]
        req = self._clearance(v, m_hi)
        g = np.maximum(np.maximum(lo[:, None] - cen, cen - hi[:, None]), 0.0)  # (M, L, 3)
        gap = np.sqrt(np.einsum("mlk,mlk->ml", g, g)) - rad
        return (gap < req[:, None]).any(axis=1)

    def check(
        self,
        q: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        cen: np.ndarray | None = None,
        rad: np.ndarray | None = None,
        groups: np.ndarray | None = None,
    ) -> np.ndarray:
        """Boolean (S,): robot ``q[k]`` (6,) at time ``t[k]`` moving at ``v[k]`` m/s keeps the separation.

        ``cen`` (S, L, 3) / ``rad`` (S, L): spheres that contain the robot capsules at each sample, if known.
        ``groups`` (S,) int: samples of one group (a move) are only of interest together: once one of them
        certainly fails, the others of its group are reported as failing without being computed.
        """
        S = q.shape[0]
        if self.forecast is None or S == 0:
            return np.ones(S, dtype=bool)
        if self._kernel is not None:
            return self._check_compiled(q, t, v, cen, rad, groups)
        n_off = len(self.offsets)
        if n_off > 1:
            t = (t[None, :] + np.asarray(self.offsets)[:, None]).reshape(-1)
            q = np.broadcast_to(q, (n_off, S, 6)).reshape(-1, 6)
            if groups is not None:
                groups = np.tile(groups, n_off)
            v = np.broadcast_to(v, (n_off, S)).reshape(-1)
            if cen is not None and rad is not None:
                cen = np.broadcast_to(cen, (n_off, *cen.shape)).reshape(-1, *cen.shape[1:])
                rad = np.broadcast_to(rad, (n_off, *rad.shape)).reshape(-1, rad.shape[1])
        elif self.offsets[0] != 0.0:
            t = t + self.offsets[0]
        req = self._required(v, t)
        n = q.shape[0]
        self.samples += n
        ok = np.ones(n, dtype=bool)
        if cen is not None and rad is not None:
            i = np.minimum(np.maximum(np.searchsorted(self._times, t, side="right") - 1, 0), self._n_pair - 1)
            lo, hi = self._lo_pair[i][:, None], self._hi_pair[i][:, None, :3]
            g = np.maximum(np.maximum(lo - cen, cen - hi), 0.0)  # (n, L, 3)
            gap = np.sqrt(np.einsum("nlk,nlk->nl", g, g)) - rad
            near = np.flatnonzero((gap < req[:, None]).any(axis=1))
        else:
            near = np.arange(n)
        if near.size:
            tn, rn = t[near], req[near]
            poses = self._poses(tn)
            if self._subsets and cen is not None and rad is not None:
                # only the robot capsules near the person's box at some sample, and only the person
                # capsules whose box over the samples' time window comes near those robot capsules
                close = gap[near] < rn[:, None]  # (n', L)
                links = np.flatnonzero(close.any(axis=0))
                cn, rdn = cen[near][:, links].reshape(-1, 3), rad[near][:, links].reshape(-1, 1)
                r_lo = (cn - rdn).min(axis=0) - rn.max()
                r_hi = (cn + rdn).max(axis=0) + rn.max()
                c_lo, c_hi = self._capsule_boxes(float(tn.min()), float(tn.max()))
                caps = np.flatnonzero(np.all((c_lo <= r_hi) & (c_hi >= r_lo), axis=1))
                a_c, d_c = self.model.robot_segments(q[near])
                if groups is not None and links.size and caps.size:
                    # a sample certainly too close fails its whole move: no exact distances for the rest
                    # (looked for at every third sample: a move that fails usually does over several)
                    some = np.arange(0, near.size, 3)
                    dead = np.zeros(near.size, dtype=bool)
                    dead[some] = (
                        self._upper_bound(a_c[..., some], d_c[..., some], poses[some], links, caps) < rn[some]
                    )
                    if dead.any():
                        ok[near[dead]] = False
                        alive = ~np.isin(groups[near], groups[near[dead]])
                        near, tn, rn, poses = near[alive], tn[alive], rn[alive], poses[alive]
                        a_c, d_c = a_c[..., alive], d_c[..., alive]
                self.exact_samples += near.size
                d = self.model.distance_to_human_paired(
                    q[near], poses, segments=(a_c, d_c), links=links, capsules=caps
                )
            else:
                self.exact_samples += near.size
                d = self.model.distance_to_human_paired(q[near], poses)
            ok[near] = d >= rn
        return ok.reshape(n_off, S).all(axis=0) if n_off > 1 else ok

    def _check_compiled(
        self,
        q: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        cen: np.ndarray | None,
        rad: np.ndarray | None,
        groups: np.ndarray | None,
    ) -> np.ndarray:
        """:meth:`check` in one compiled pass (:func:`app.planning._kernels.sample_separation_ok`): the same
        broad phase and exact distances, with the exact stage stopping at the first capsule pair that is too
        close and skipping the rest of a group once one of its samples failed."""
        S = q.shape[0]
        n_off = len(self.offsets)
        t_all = np.asarray(t, dtype=np.float64)[None, :] + self._k_offsets[:, None]
        v_all = np.broadcast_to(np.asarray(v, dtype=np.float64), (n_off, S)).reshape(-1)
        req = self._required(v_all, t_all.reshape(-1)).reshape(n_off, S)
        use_spheres = cen is not None and rad is not None
        if use_spheres:
            cen_k, rad_k = _kernels.as_f64(cen), _kernels.as_f64(rad)
        else:
            cen_k, rad_k = np.zeros((1, 1, 3)), np.zeros((1, 1))
        if groups is None:
            groups_k, n_groups = _NO_IDS, 0
        else:
            groups_k = _kernels.as_i64(groups)
            n_groups = int(groups_k.max()) + 1
        ok, exact = _kernels.sample_separation_ok(
            _kernels.as_f64(q),
            t_all,
            _kernels.as_f64(req),
            cen_k,
            rad_k,
            use_spheres,
            groups_k,
            n_groups,
            *self._k_forecast,
            *self._kernel,
        )
        self.samples += n_off * S
        self.exact_samples += exact
        return ok

    def _upper_bound(
        self, a_c: np.ndarray, d_c: np.ndarray, poses: np.ndarray, links: np.ndarray, caps: np.ndarray
    ) -> np.ndarray:
        """An upper bound (n,) of the surface distance between the robot capsules ``links`` (segments
        ``a_c``, ``d_c`` (L, 3, n)) and the person capsules ``caps`` in ``poses`` (n, J, 3): the distance
        between a point on a robot capsule's axis (either end) and a joint on a person capsule's axis, less
        both radii, is never below the capsules' distance."""
        ia, ib, hr = self._cap_ends
        r_joint = np.full(poses.shape[1], -np.inf)
        np.maximum.at(r_joint, ia[caps], hr[caps])
        np.maximum.at(r_joint, ib[caps], hr[caps])
        joints = np.flatnonzero(np.isfinite(r_joint))
        a, d = a_c[links], d_c[links]
        pts = np.concatenate([a, a + d])  # (2L', 3, n): both ends of each axis
        jt = poses[:, joints].transpose(2, 1, 0)  # (3, J', n)
        sq = np.zeros((pts.shape[0], joints.size, pts.shape[2]))
        for k in range(3):
            diff = pts[:, k, None, :] - jt[k][None]
            diff *= diff
            sq += diff
        dist = np.sqrt(sq, out=sq)
        dist -= np.tile(self._robot_r[links], 2)[:, None, None] + r_joint[joints][None, :, None]
        return dist.reshape(-1, dist.shape[2]).min(axis=0)

    def _capsule_boxes(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """Boxes (M, 3) x 2 that contain each person capsule over the window [t0, t1]."""
        times, H = self._times, self._H
        i0 = min(max(int(np.searchsorted(times, t0, side="right")) - 1, 0), H - 1)
        i1 = max(min(int(np.searchsorted(times, t1, side="left")), H - 1), i0)
        k = (i1 - i0 + 1).bit_length() - 1
        a, b = i0, i1 - (1 << k) + 1
        return (
            np.minimum(self._clo_tab[k][a], self._clo_tab[k][b]),
            np.maximum(self._chi_tab[k][a], self._chi_tab[k][b]),
        )


class Planner:
    """Time-variant A* over a roadmap, against a forecast of the person.

    Args:
        roadmap: The static roadmap (shared, never modified).
        collision: The collision model (:class:`app.planning.collision.CollisionModel`, or anything with
            the methods of :class:`RobotModel`).
        config: Search settings.
        timer: Monotonic clock for deadlines and ``compute_s`` (seconds); injectable for tests.
        warm_up: With the compiled checks, load the compiled kernels now with one small query
            (:meth:`_warm_up`) rather than in the first real one.

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
        warm_up: bool = True,
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
        # the compiled row-wise _align (only with the compiled collision model: a NumPy model stays NumPy)
        compiled = bool(getattr(collision, "compiled", False))
        self._k_align = (_kernels.as_f64(self.q_min), _kernels.as_f64(self.q_max)) if compiled else None
        # path acceleration in "fraction of full speed per second"
        self._A = float(np.min(self.qdd_max / self.qd_max)) * cfg.accel_fraction
        self._ik = roadmap.ik
        self._valid = roadmap.valid
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
        self._station_array = np.array(sorted(set(roadmap.station_nodes.values())), dtype=np.int64)
        # the exact verification can reuse its forward kinematics when the model takes segments
        opts = _paired_options(collision)
        self._subsets_ok = {"links", "capsules"} <= opts
        self._segments_ok = "segments" in opts and hasattr(collision, "robot_segments")
        self._static_segments_ok = self._segments_ok and all(
            "segments" in inspect.signature(getattr(collision, name)).parameters
            for name in ("in_static_collision", "self_collision")
        )
        self._robot_r = np.asarray(collision.robot_capsules(np.zeros((1, 6)))[2], dtype=np.float64)
        # the fused compiled checks, when the model is the (compiled) UR5e capsule model
        get_geometry = getattr(collision, "kernel_geometry", None)
        self._kernel_geometry = get_geometry() if callable(get_geometry) and self._segments_ok else None
        if self._kernel_geometry is not None:  # the node tables as the compiled move check reads them
            n_rows = roadmap.num_nodes * NUM_BRANCHES
            self._k_tables = (
                _kernels.as_f64(self._pts_all.reshape(n_rows, -1, 3)),
                _kernels.as_f64(self._cen_all.reshape(n_rows, -1, 3)),
                _kernels.as_f64(self._rad_all.reshape(n_rows, -1)),
            )
            self._k_lever = _kernels.as_f64(self._lever)
            self._k_q_lo, self._k_q_hi = _kernels.as_f64(self.q_min), _kernels.as_f64(self.q_max)
            self._k_moved_by = _kernels.as_i64(self._moved_by)
            self._k_ik = _kernels.as_f64(self._ik)
            self._k_speed_factor = float(cfg.speed_factor)
            self._k_sample_dt = float(cfg.sample_dt_s)
        self._human_r_max = float(np.max(collision.human_capsules(np.zeros((1, NUM_JOINTS, 3)))[2]))
        # which joints each person capsule runs between (joint indices fed in as coordinates) and its radius
        coded = np.repeat(np.arange(NUM_JOINTS, dtype=np.float64)[None, :, None], 3, axis=2)
        ha, hb, hr = collision.human_capsules(coded)
        self._cap_ends = (
            np.asarray(ha)[0, :, 0].astype(np.int64),
            np.asarray(hb)[0, :, 0].astype(np.int64),
            np.asarray(hr, dtype=np.float64),
        )
        self._next_cache: dict[int, list[int]] = {}
        self._next_cache_k: dict[int, np.ndarray] = {}
        self._static_memo: dict[tuple[int, int, int, int], int] = {}
        for node in roadmap.station_nodes.values():
            if self._valid[node].any():
                self._heuristic_table(node)
        if warm_up and self._kernel_geometry is not None and self._k_align is not None:
            self._warm_up()

    def _warm_up(self) -> None:
        """One small batched query between two stations with a person far away, so that the compiled
        kernels are loaded (numba's cache) here and not in the first real query (about 0.1 s once per
        process). Its only lasting effect is the static-check memo's entries (pure functions of the
        roadmap)."""
        stations = [n for n in self.roadmap.station_nodes.values() if self._valid[n].any()]
        if len(stations) < 2:
            return
        from app.prediction.forecast import HumanForecast

        far = HumanForecast(
            t0=0.0,
            times=np.array([0.0, 1.0]),
            joints=np.full((2, NUM_JOINTS, 3), 50.0),
            margins=np.array([0.1, 0.1]),
        )
        q0 = self._ik[stations[0]][np.flatnonzero(self._valid[stations[0]])[0]]
        goal = int(stations[1])
        self.plan(q_start=q0, t_start=0.0, goal=goal, forecast=far, workers=2)
        # what that query did not need: failed moves, deferred and pushed-back states, the approach probe
        sep = self._separation(far, extra_m=0.0)
        run = _Run(
            self, q0, 0.0, sep, goal=goal, stop_time=None, hold_s=0.0, h_tab=self._heuristic_table(goal),
            t_last=math.inf,
        )  # fmt: skip
        run.alternatives(np.zeros(0, dtype=np.int64))
        ol = _OpenList(run)
        ol.push((np.zeros(1, dtype=np.int64), np.zeros(1), np.zeros(1)))
        ol.push_back(0)
        ol.release(0)
        self._align(self._ik[:1, 0], self._ik[:1, 0])
        self.collision.distance_to_human_paired(q0[None], far.joints[:1])

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
        # the same tables with one row per (CSR entry, parent branch): row = e * 8 + b
        self._ord_flat = self._ord_tab.reshape(E * NUM_BRANCHES, R).astype(np.int64)
        self._L_flat = self._L_tab.reshape(E * NUM_BRANCHES, R)
        self._same_flat = self._same_tab.reshape(E * NUM_BRANCHES, R)
        self._indptr = rm.indptr
        self._indices = rm.indices
        self._k_indptr, self._k_indices = _kernels.as_i64(rm.indptr), _kernels.as_i64(rm.indices)
        self._max_degree = int(np.diff(rm.indptr).max(initial=0))
        self._src_state = (src[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)
        # per row, the nearest branch's configuration minus the parent's, shifted by multiples of 2 pi next
        # to it (without the limits: a shifted parent gets the same shift, see _Run.speculate)
        q_u = self._ik[np.repeat(src, NUM_BRANCHES), np.tile(np.arange(NUM_BRANCHES), E)]
        q_v = self._ik[np.repeat(rm.indices, NUM_BRANCHES), self._ord_flat[:, 0]]
        self._delta0 = q_v + _TWO_PI * np.rint((q_u - q_v) * (1.0 / _TWO_PI)) - q_u
        self._ord_list = self._ord_flat[:, 0].tolist()
        self._L_list = self._L_flat[:, 0].tolist()
        self._same_list = self._same_flat[:, 0].tolist()
        self._indices_list = rm.indices.tolist()

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
        if self._k_align is not None and q.ndim == 2 and q.shape == q_ref.shape:
            return _kernels.align_rows(_kernels.as_f64(q), _kernels.as_f64(q_ref), *self._k_align)
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

    def _static_bad(self, q: np.ndarray, segments: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Configurations (n, 6) in collision with the static scene or themselves, or beyond the limits.

        ``segments``: the robot's segments for ``q`` (:meth:`CollisionModel.robot_segments`), if known."""
        bad = ~self._within_limits(q)
        sb = self._static_boxes
        kw = {} if segments is None else {"segments": segments}
        if sb is None:
            need = np.arange(q.shape[0])
        else:
            blo, bhi, pairs = sb
            if segments is None:
                a, b, r = self.collision.robot_capsules(q)
            else:
                a, r = segments[0].transpose(2, 0, 1), self._robot_r
                b = a + segments[1].transpose(2, 0, 1)
            lo = np.minimum(a, b) - r[:, None]  # (n, L, 3)
            hi = np.maximum(a, b) + r[:, None]
            g = np.maximum(
                np.maximum(blo[None, None] - hi[:, :, None], lo[:, :, None] - bhi[None, None]), 0.0
            )
            gap = np.sqrt(np.einsum("nlbk,nlbk->nlb", g, g))
            near = (gap <= self.config.static_margin_m + 1e-9) & pairs[None]
            need = np.flatnonzero(near.any(axis=(1, 2)))
        if need.size:
            sub = {} if segments is None else {"segments": (segments[0][..., need], segments[1][..., need])}
            bad[need] |= self.collision.in_static_collision(
                q[need], margin_m=self.config.static_margin_m, **sub
            )
        bad |= self.collision.self_collision(q, **kw)
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
        *,
        same_move: np.ndarray | None = None,
    ) -> np.ndarray:
        """Static check (1 free, -1 blocked) of moves q_par -> target that the roadmap did not check, from
        node ``u`` at branch ``bu`` (-1: the start) to node ``cv`` at branch ``b``; memoised per
        (node, branch, node, branch) when the move is the one between the stored branch configurations
        (``same_move`` (M,) where the caller knows it).

        The memo belongs to the planner (never the roadmap) and only ever gains entries that are pure
        functions of the roadmap, so concurrent queries may share it.
        """
        out = np.zeros(u.shape[0], dtype=np.int8)
        keys: list[tuple[int, int, int, int] | None] = [None] * u.shape[0]
        if same_move is not None:
            on = np.flatnonzero(same_move)
            same_move = np.ones(on.size, dtype=bool)
        else:
            on = np.flatnonzero(u >= 0)
            if on.size:
                ref = self._ik[u[on], bu[on]]
                ref_t = self._align(self._ik[cv[on], b[on]], ref)
                same_move = np.abs((ref_t - ref) - (target[on] - q_par[on])).max(axis=1) <= 1e-9
        if on.size:
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
            self._next_cache[goal] = self._next_rows(tab)
            self._next_cache_k[goal] = np.asarray(self._next_cache[goal], dtype=np.int64)
        return tab

    def _next_rows(self, h: np.ndarray) -> list[int]:
        """Per node branch (index ``node * 8 + branch``), the option-table row of the move a search would
        try first that is best by ``L / cruise + h`` (the next step of the static shortest path through the
        nearest-branch moves), or -1: the speculative chain (:meth:`_Run.speculate`) follows it."""
        rows = np.arange(self._L_flat.shape[0])
        src = self._src_state
        cost = (
            self._L_flat[:, 0] / self.config.speed_fraction
            + h.reshape(-1)[self._indices[rows // NUM_BRANCHES] * NUM_BRANCHES + self._ord_flat[:, 0]]
        )
        order = np.lexsort((cost, src))
        first = order[np.r_[True, src[order][1:] != src[order][:-1]]]
        first = first[np.isfinite(cost[first])]
        out = np.full(self.roadmap.num_nodes * NUM_BRANCHES, -1, dtype=np.int64)
        out[src[first]] = first
        return out.tolist()

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
        from scipy.sparse import csr_matrix  # scipy is only loaded with a planner

        return csr_matrix((cost[keep], (dst[keep], src[keep])), shape=(S, S))

    def _to_goal_neighbours(self, goal: int) -> np.ndarray:
        """(N, 8) static time (s, cruise speed, as :meth:`_static_to_go`) from every node branch to a node
        branch that has a move into ``goal`` (0 there; +inf where none can be reached)."""
        rm = self.roadmap
        entries = np.flatnonzero(rm.indices == goal)
        src = np.searchsorted(rm.indptr, entries, side="right") - 1
        states = (src[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)
        rows = (entries[:, None] * NUM_BRANCHES + np.arange(NUM_BRANCHES)).reshape(-1)
        states = states[np.isfinite(self._L_flat[rows, 0]) & self._valid.reshape(-1)[states]]
        if states.size == 0:
            return np.full((rm.num_nodes, NUM_BRANCHES), np.inf)
        from scipy.sparse.csgraph import dijkstra

        d = dijkstra(self._rev_graph, directed=True, indices=states, min_only=True)
        return np.asarray(d).reshape(-1, NUM_BRANCHES)

    def _static_to_go(self, goal: int) -> np.ndarray:
        """Static time-to-go (N * 8,) in s from every node branch to any valid branch of ``goal`` over the
        moves the search can take (nearest ``max_branch_tries`` branches per edge), each timed at the cruise
        speed without acceleration: a lower bound of any search path's duration (its moves last at least
        their length / cruise speed), +inf where the goal cannot be reached."""
        sources = goal * NUM_BRANCHES + np.flatnonzero(self._valid[goal])
        if sources.size == 0:
            return np.full(self.roadmap.num_nodes * NUM_BRANCHES, np.inf)
        from scipy.sparse.csgraph import dijkstra

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
        ssm_extra: tuple[float, np.ndarray] | None = None,
    ) -> _Separation:
        return _Separation(
            self.collision,
            forecast,
            self.config.ssm,
            extra_m=extra_m,
            offsets=offsets,
            floor_m=floor_m,
            subsets=self._subsets_ok and self._segments_ok,
            cap_ends=self._cap_ends,
            robot_r=self._robot_r,
            kernel=self._kernel_geometry,
            ssm_extra=ssm_extra,
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
        timing: GovernorModel | None = None,
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
            timing: The speed governor's model: when given (with a forecast), the path found is verified
                at the timing the governor is predicted to give it (:mod:`app.planning.ssm_timing`: the
                person where they will be when the robot really gets there), and ``arrival_s`` is that
                timing's arrival; the plan keeps its full-speed timing for the robot to execute.

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
        ssm_extra = None
        if timing is not None and forecast is not None and cfg.ssm_aware_search:
            table = timing.extra_clearance(v_creep_mps=cfg.ssm_creep_mps, decel_mps2=cfg.ssm_brake_decel_mps2)
            ssm_extra = (0.05, table)
        for offsets in attempts:
            sep = self._separation(
                forecast, extra_m=cfg.corridor_margin_m, offsets=offsets, ssm_extra=ssm_extra
            )
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
            done = None
            if cfg.shortcut and (deadline is None or self._timer() < deadline):
                short = self._shortcut(waypoints, sep, hold_s=cfg.goal_hold_s)
                if short is not None:  # verified like any plan; the search's own path is the fallback
                    done = self._finish(short, qd0, forecast, hold_s=cfg.goal_hold_s, timing=timing)
            if done is None:
                done = self._finish(waypoints, qd0, forecast, hold_s=cfg.goal_hold_s, timing=timing)
            if done is not None:
                return PlanResult(True, done[0], "ok", expanded, self._timer() - t0, done[1], done[2])
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
                return PlanResult(True, done[0], "ok", expanded, self._timer() - t0, done[1], done[2])
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
        :func:`app.safety.ssm.forecast_clearance` (``S_r + S_s + C + Z_r + max(Z_d, margin)``) for the
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
        if self._kernel_geometry is not None and forecast is not None:
            view = _compiled_view(traj)
            if view is not None:
                return self._verify_compiled(traj, view, forecast, ts, static=static, floor_m=floor_m)
        q = traj.q(ts)
        bad = ~self._within_limits(q)
        # forward kinematics once for the static scene and the person (when the model takes segments)
        segs = self.collision.robot_segments(q) if self._static_segments_ok else None
        if static:
            moving = np.flatnonzero((ts >= traj.t_start) & (ts <= traj.t_end))
            if moving.size:
                sub = None if segs is None else (segs[0][..., moving], segs[1][..., moving])
                bad[moving] |= self._static_bad(q[moving], sub)
        if forecast is not None:
            joints, margins = forecast.poses_at(ts)
            if self._segments_ok:
                bad |= self._separation_bad(traj, ts, q, joints, margins, floor_m, segs)
            else:
                v = self.robot_speed(traj, ts)
                d = self.collision.distance_to_human_paired(q, joints)
                req = forecast_clearance(v, margins, self.config.ssm)
                if floor_m is not None:
                    req = np.minimum(req, floor_m)
                bad |= d < req
        if not np.any(bad):
            return None
        return float(ts[np.argmax(bad)])

    def _verify_compiled(
        self,
        traj: Any,
        view: tuple[Trajectory, Callable[[np.ndarray], np.ndarray]],
        forecast: HumanForecast,
        ts: np.ndarray,
        *,
        static: bool,
        floor_m: float | None,
    ) -> float | None:
        """:meth:`_verify` with the limits and the separation in one compiled pass that stops at the first
        failing sample (:func:`app.planning._kernels.trajectory_first_violation`); the static scene, where
        asked for, in NumPy first (the compiled pass then only looks at the samples before its first
        failure). ``view``: the :class:`Trajectory` that ``traj`` evaluates and the map from wall times to
        its times (:func:`_compiled_view`)."""
        n = ts.shape[0]
        first = n
        if static:
            moving = np.flatnonzero((ts >= traj.t_start) & (ts <= traj.t_end))
            if moving.size:
                q = traj.q(ts[moving])
                bad = ~self._within_limits(q)
                segs = self.collision.robot_segments(q) if self._static_segments_ok else None
                bad |= self._static_bad(q, segs)
                if bad.any():
                    first = int(moving[np.argmax(bad)])
        ssm = self.config.ssm
        f64 = _kernels.as_f64
        base, path_times = view
        eps = 1e-4
        t_wall = f64(ts[:first])
        k = _kernels.trajectory_first_violation(
            t_wall,
            f64(path_times(t_wall)),
            f64(path_times(t_wall + eps)),
            *base._kernel_knots(),
            eps,
            self._k_q_lo,
            self._k_q_hi,
            f64(forecast.times),
            f64(forecast.joints),
            f64(forecast.margins),
            float(forecast.growth_mps),
            max(float(forecast.max_margin_m), float(forecast.margins.max())),
            ssm.robot_time_s,
            ssm.intrusion_m,
            ssm.z_robot_m,
            ssm.z_human_m,
            math.inf if floor_m is None else float(floor_m),
            self._human_r_max,
            *self._kernel_geometry,
        )
        if k >= 0:
            first = k
        return None if first == n else float(ts[first])

    def _separation_bad(
        self,
        traj: Trajectory,
        ts: np.ndarray,
        q: np.ndarray,
        joints: np.ndarray,
        margins: np.ndarray,
        floor_m: float | None,
        segs: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """(K,) bool: samples of ``traj`` at ``ts`` (configurations ``q``) closer to the person (poses
        ``joints`` (K, J, 3), margins (K,)) than :func:`forecast_clearance` for the robot's speed there.

        The same requirement as :meth:`robot_speed` + ``distance_to_human_paired`` (exact), with the forward
        kinematics done once per sample time and the exact distance only where a capsule's bounding sphere
        comes within the requirement of the box around the person's pose."""
        eps = 1e-4
        model = self.collision
        a0, d0 = model.robot_segments(q) if segs is None else segs  # (L, 3, K)
        a1, d1 = model.robot_segments(traj.q(ts + eps))
        step = np.maximum(
            np.sqrt(np.einsum("lik,lik->lk", a1 - a0, a1 - a0)),
            np.sqrt(np.einsum("lik,lik->lk", (a1 + d1) - (a0 + d0), (a1 + d1) - (a0 + d0))),
        )
        v = step.max(axis=0) / eps
        req = forecast_clearance(v, margins, self.config.ssm)
        if floor_m is not None:
            req = np.minimum(req, floor_m)
        cen = a0 + 0.5 * d0
        rad = 0.5 * np.sqrt(np.einsum("lik,lik->lk", d0, d0)) + self._robot_r[:, None]
        jt = joints.transpose(2, 0, 1)  # (3, K, J)
        lo = (jt.min(axis=2) - self._human_r_max)[None]  # (1, 3, K)
        hi = (jt.max(axis=2) + self._human_r_max)[None]
        g = np.maximum(np.maximum(lo - cen, cen - hi), 0.0)
        gap = np.sqrt(np.einsum("lik,lik->lk", g, g)) - rad
        close = gap < req[None]  # (L, K)
        near = np.flatnonzero(close.any(axis=0))
        bad = np.zeros(q.shape[0], dtype=bool)
        if near.size == 0:
            return bad
        segments = (a0[..., near], d0[..., near])
        if not self._subsets_ok:
            d = model.distance_to_human_paired(q[near], joints[near], segments=segments)
        else:
            # only the capsules that come near: robot links near the person's box at some sample, person
            # capsules whose box over those samples comes near the box of those links
            links = np.flatnonzero(close[:, near].any(axis=1))
            r_max = float(req[near].max())
            cl, rl = cen[links][..., near], rad[links][:, near, None].transpose(0, 2, 1)
            r_lo = (cl - rl).min(axis=2).min(axis=0) - r_max
            r_hi = (cl + rl).max(axis=2).max(axis=0) + r_max
            jn = joints[near]
            ha, hb, hr = model.human_capsules(np.stack([jn.min(axis=0), jn.max(axis=0)]))
            # a capsule between two joints lies within the box of their ranges over the samples
            c_lo = np.minimum(ha[0], hb[0]) - hr[:, None]
            c_hi = np.maximum(ha[1], hb[1]) + hr[:, None]
            caps = np.flatnonzero(np.all((c_lo <= r_hi) & (c_hi >= r_lo), axis=1))
            d = model.distance_to_human_paired(
                q[near], joints[near], segments=segments, links=links, capsules=caps
            )
        bad[near] = d < req[near]
        return bad

    def _finish(
        self,
        waypoints: Plan,
        qd0: np.ndarray | None,
        forecast: HumanForecast | None,
        *,
        hold_s: float,
        floor_m: float | None = None,
        timing: GovernorModel | None = None,
    ) -> tuple[Plan, Trajectory, float] | None:
        """The search's waypoints as a verified trajectory: the fitted spline, else straight moves that stop
        at each waypoint, else the spline slower; with the predicted arrival (s, runtime clock).

        With ``timing`` (and a forecast) each candidate is verified at the timing the governor is predicted
        to give it (:class:`app.planning.ssm_timing.PredictedTiming`), and the arrival is the predicted
        one; without, at its own timing."""

        def check(traj: Trajectory) -> tuple[float | None, float]:
            view: Any = traj
            if timing is not None and forecast is not None:
                view = PredictedTiming.of(traj, forecast, self.collision, timing)
            end = view.t_end + hold_s
            return self._verify(view, forecast, view.t_start, end, floor_m=floor_m), view.t_end

        traj = self._fit(waypoints, qd0)
        if traj is None:
            return None
        viol, arrival = check(traj)
        if viol is not None and (qd0 is None or not np.any(np.asarray(qd0) != 0.0)):
            # the spline cuts a corner: stopping at every waypoint keeps the robot on the straight moves
            # the search checked (slower, so it is verified again)
            logger.debug("fitted trajectory violates at t=%.3f; trying straight moves", viol)
            straight = self._fit_stops(waypoints)
            if straight is not None:
                viol, arrival = check(straight)
                if viol is None:
                    traj = straight
        if viol is not None:
            # the fitted spline peaks faster than the search's constant-speed moves, and the clearance grows
            # with the speed: the same path, slower, asks for less (and is verified again)
            for factor in _STRETCH_FACTORS:
                t0 = float(waypoints.times[0])
                times = t0 + (np.asarray(waypoints.times) - t0) * factor
                slower = Plan(times=times, q=waypoints.q, nodes=waypoints.nodes)
                retimed = self._fit(slower, qd0)
                if retimed is None:
                    continue
                viol_r, arrival_r = check(retimed)
                if viol_r is None:
                    return retimed.to_plan(_map_nodes(slower, retimed)), retimed, arrival_r
            logger.debug("fitted trajectory violates at t=%.3f (%.3f..%.3f)", viol, traj.t_start, traj.t_end)
            return None
        return traj.to_plan(_map_nodes(waypoints, traj)), traj, arrival

    def _fit_stops(self, plan: Plan) -> Trajectory | None:
        """A trajectory at rest at every waypoint: each segment a straight joint move with zero end
        velocities (cubic Hermite), at the waypoints' times or later where the limits need longer
        (peak velocity 1.5 dq / h, peak acceleration 6 dq / h^2 per joint)."""
        times, q = plan.times, plan.q
        if times.shape[0] < 2:
            return None
        dq = np.abs(np.diff(q, axis=0))
        need = np.maximum(
            np.max(1.5 * dq / self.qd_max, axis=1), np.sqrt(np.max(6.0 * dq / self.qdd_max, axis=1))
        )
        h = np.maximum(np.maximum(np.diff(times), need), 1e-3)
        t = np.concatenate([[times[0]], times[0] + np.cumsum(h)])
        return Trajectory(t, q.copy(), np.zeros_like(q))

    # ------------------------------------------------------------------------------------------ shortcut
    def _shortcut(self, waypoints: Plan, sep: _Separation, *, hold_s: float) -> Plan | None:
        """The search's path with runs of waypoints replaced by single straight joint moves, re-timed.

        Roadmap paths follow straight TCP segments between samples, so in joint space they zig-zag and the
        spline through them has to slow down at every reversal. From each kept waypoint (the start first)
        the farthest later waypoint is taken that one straight joint move reaches (a) free of the static
        scene and of self-collision (:meth:`_static_free`) and (b) keeping the forecast clearance over time,
        checked as the search checks its moves (:meth:`_moves_ok`: the path-speed profile from the path
        speed reached there, braking to rest into the goal, with the goal hold). The move straight from the
        start to the goal is checked first (on a free way the only check); after that, all candidates of a
        waypoint are checked in one vectorised call, together with the search's own move to the next
        waypoint (re-timed, at the cruise speed or one of ``slow_speed_fractions``), which is kept where no
        shortcut passes. If even that fails at its new time, the whole shortcut is given up. After
        ``shortcut_rounds`` such calls one more call checks the move straight to the goal and, as the
        alternative, the rest of the search's moves re-timed one after the other (the last one also slower),
        so the cost stays bounded: at most ``shortcut_rounds + 1`` vectorised forecast checks and
        ``shortcut_rounds + 1`` static ones.

        Waits stay as they are: only the part after the last wait is shortened (its moves depart from rest
        at the wait's end, as the search timed them); the part before keeps the search's times.

        Returns:
            The shortened plan (times from the profile), or None when nothing was shortened or a move failed.
            It is only a candidate: the caller fits and verifies it (:meth:`_finish`) like any plan and
            falls back to ``waypoints``.
        """
        cfg = self.config
        times, q, nodes = waypoints.times, waypoints.q, waypoints.nodes
        still = np.flatnonzero(np.all(np.abs(np.diff(q, axis=0)) <= 1e-12, axis=1))  # waits
        s0 = int(still[-1]) + 1 if still.size else 0
        qs = q[s0:]
        n = qs.shape[0]
        if n < 3:
            return None
        pts, cen, rad = self._points_and_spheres(qs)
        f, A = cfg.speed_fraction, self._A
        speeds = np.array([f, *sorted((x for x in cfg.slow_speed_fractions if x < f), reverse=True)])

        def attempt(
            ia: np.ndarray, js: np.ndarray, fc: np.ndarray, t_dep: np.ndarray, u: np.ndarray
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """Moves qs[ia] -> qs[js] departing at t_dep with path speed u at cruise speeds fc: (ok, h, exit
            speed). The static scene is checked for shortcuts only (a move to the next waypoint is the
            search's own)."""
            L = self._metric(qs[js] - qs[ia])
            end = js == n - 1
            u0 = np.minimum(u, fc)
            h, u1, _ = _profile_arrays(u0, L, fc, A, end)
            h = np.where(L > 1e-12, np.maximum(h, cfg.min_edge_s), h)
            ok = np.ones(js.size, dtype=bool)
            cut = np.flatnonzero(js > ia + 1)
            if cut.size:
                ok[cut] = self._static_free(qs[ia[cut]], qs[js[cut]])
            live = np.flatnonzero(ok)
            if live.size and sep.forecast is not None:
                al, jl = ia[live], js[live]
                ok[live] = self._moves_ok(
                    sep,
                    qs[al],
                    pts[al],
                    cen[al],
                    rad[al],
                    np.zeros(live.size, dtype=np.int64),
                    np.zeros(live.size, dtype=np.int64),
                    qs[jl],
                    t_dep[live],
                    h[live],
                    u0[live],
                    L[live],
                    end[live],
                    fc[live],
                    end[live],
                    hold_s,
                    target_geometry=(pts[jl], cen[jl], rad[jl]),
                )
            return ok, h, u1

        keep, t_new = [0], [float(times[s0])]
        i, t, u = 0, float(times[s0]), 0.0
        rounds = 0
        while i < n - 1 and rounds < cfg.shortcut_rounds:
            j, top = -1, n
            if rounds == 0 and i + 2 <= n - 1:  # straight to the goal: on a free way the only check
                ok, h, u1 = attempt(
                    np.array([i]), np.array([n - 1]), speeds[:1], np.array([t]), np.array([u])
                )
                rounds += 1
                if ok[0]:
                    j, hj, uj = n - 1, float(h[0]), float(u1[0])
                top = n - 1
            if j < 0:
                if rounds >= cfg.shortcut_rounds:
                    break
                # every shortcut from here (the farthest that passes wins) and, in the same check, the
                # search's own move to the next waypoint at each speed (the fastest that passes is the
                # fallback)
                cuts = np.arange(i + 2, top)
                js = np.concatenate([cuts, np.full(speeds.size, i + 1)])
                m = js.size
                fc = np.concatenate([np.full(cuts.size, f), speeds])
                ok, h, u1 = attempt(np.full(m, i), js, fc, np.full(m, t), np.full(m, u))
                rounds += 1
                good = np.flatnonzero(ok)
                if good.size == 0:
                    return None
                passed_cuts = good[good < cuts.size]
                k = int(passed_cuts[-1]) if passed_cuts.size else int(good[0])
                j, hj, uj = int(js[k]), float(h[k]), float(u1[k])
            i, t, u = j, t + hj, uj
            keep.append(j)
            t_new.append(t)
        if keep[-1] == len(keep) - 1:
            return None  # nothing shortened (nor would the rest be)
        if i < n - 1:
            # the rounds are used up: straight to the goal, or else the rest of the search's moves re-timed
            # at the cruise speed one after the other (the last, into the goal, also slower), in one call
            rest = np.arange(i, n - 1)
            dep, u_in = np.empty(rest.size), np.empty(rest.size)
            t_k, u_k = t, u
            for k, a in enumerate(rest.tolist()):
                L = float(self._metric(qs[a + 1] - qs[a]))
                h_k, u_next, _ = _profile_py(u_k, L, f, A, a + 1 == n - 1)
                dep[k], u_in[k] = t_k, u_k
                t_k, u_k = t_k + (max(h_k, cfg.min_edge_s) if L > 1e-12 else h_k), u_next
            d = int(rest.size > 1)  # the move straight to the goal first, when it is a shortcut
            slow = speeds[1:]
            m = rest.size
            ia = np.concatenate([np.full(d, i), rest, np.full(slow.size, n - 2)])
            js = np.concatenate([np.full(d, n - 1), rest + 1, np.full(slow.size, n - 1)])
            ok, h, _ = attempt(
                ia,
                js,
                np.concatenate([np.full(d + m, f), slow]),
                np.concatenate([np.full(d, t), dep, np.full(slow.size, dep[-1])]),
                np.concatenate([np.full(d, u), u_in, np.full(slow.size, u_in[-1])]),
            )
            chain = ok[d : d + m].copy()
            h_chain = h[d : d + m].copy()
            last = np.flatnonzero(ok[d + m :])
            if not chain[-1] and last.size:  # the goal reached more slowly
                chain[-1], h_chain[-1] = True, h[d + m + int(last[0])]
            if d and ok[0]:
                keep.append(n - 1)
                t_new.append(t + float(h[0]))
            elif chain.all():
                keep.extend((rest + 1).tolist())
                t_new.extend((dep + h_chain).tolist())
            else:
                return None
        idx = np.concatenate([np.arange(s0), s0 + np.asarray(keep)])
        return Plan(
            times=np.concatenate([times[:s0], t_new]),
            q=q[idx],
            nodes=nodes[idx],
        )

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
        """Lazy time-variant A*. Returns (waypoints or None, validated expansions, reason).

        Successor moves are generated for whole batches of states at once from the precomputed tables and
        pushed unchecked, timed by the path-speed profile; a move is checked (static scene where the roadmap
        did not check it, forecast person, wait, goal hold) only when its state is popped, ``workers``
        states at a time in one vectorised check. A failed move pushes its alternatives: the next branches,
        the slower speeds, the waits. The f-values of unchecked states are their times + the heuristic, so
        the order and the result are those of A* over the checked moves.
        """
        cfg = self.config
        W = max(int(workers), 1)
        h_tab = None if goal is None else self._heuristic_table(goal)
        # the latest arrival after which the person blocks the goal for good
        t_last = math.inf if goal is None else self._latest_goal_arrival(sep, goal, t_start, hold_s)
        t_last = min(t_last, t_start + cfg.max_plan_s)
        run = _Run(
            self,
            q_start,
            t_start,
            sep,
            goal=goal,
            stop_time=stop_time,
            hold_s=hold_s,
            h_tab=h_tab,
            t_last=t_last,
        )
        run.row[0] = _NO_ROW
        if run.compiled:
            return self._search_compiled(run, t_start, sep, goal=goal, hold_s=hold_s, W=W, deadline=deadline)
        AT = run.AT
        heap: list[tuple[float, float, int]] = []

        def push(got: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
            ids, keys, ts = got
            for item in zip(keys.tolist(), (-ts).tolist(), ids.tolist(), strict=True):
                heapq.heappush(heap, item)

        push(run.start_moves())
        goal_i = -2 if goal is None else goal
        stop = math.inf if stop_time is None else stop_time
        # lookahead: the best popped state of a batch takes a chain of moves ahead along the static
        # shortest path into the same batch (the batch's other slots go to the next states in order)
        spec_len = W // 2 if goal is not None and W > 1 else 0
        n_batches = 0
        spec_rate = 1.0  # recent share of lookahead moves that passed (with the state they start from)
        chain_ids = _NO_IDS
        expanded = 0
        w_h = cfg.heuristic_weight
        # when the search gets long: can the goal still be entered once the person comes to rest?
        probed = goal is None or sep.forecast is None
        t_static = sep.t_static
        blocked_from: float | None = None

        # states popped before their (speculative) parent was accepted wait here for it
        deferred: dict[int, list[tuple[float, float, int]]] = {}

        def accept(sid: int, t: float, node: int) -> bool:
            """Mark a checked state expanded; True when it ends the search."""
            nonlocal expanded
            AT[node] = t
            run.accepted[sid] = True
            expanded += 1
            if node == goal_i or t >= stop:
                return True
            for entry in deferred.pop(sid, ()):
                heapq.heappush(heap, entry)
            return False

        while heap:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            popped: list[int] = []
            finals: list[tuple[float, float, int]] = []
            n_batches += 1
            W_b = min(W, 8 + 4 * n_batches)  # the batch grows: the first steps have few states worth checking
            while heap and len(batch) < W_b:
                entry = heapq.heappop(heap)
                sid = entry[2]
                node = int(run.node[sid])
                t = -entry[1]
                if t >= AT[node] - _EPS_T:
                    continue  # a checked state reached this node no later
                if blocked_from is not None and (
                    (node != goal_i and t + run.h_pred[node, run.branch[sid]] >= run.t_nongoal)
                    or t + (entry[0] - t) / w_h > run.t_last + _EPS_T
                ):
                    continue  # pruned after the approach probe
                par = int(run.parent[sid])
                if not run.accepted[par]:  # a speculative chain's state whose parent is not through yet
                    if run.status[par] != 2:
                        deferred.setdefault(par, []).append(entry)
                    continue
                final = node == goal_i or t >= stop
                st = int(run.status[sid])
                if final and batch and st != 0:  # states popped before it (f <= its f) may improve it
                    heapq.heappush(heap, entry)
                    break
                if st == 1:  # checked ahead of time (a speculative chain): passed
                    if accept(sid, t, node):
                        return run.reconstruct(sid), expanded, "ok"
                    push(run.children(np.array([sid], dtype=np.int64)))
                    continue
                if st == 2:
                    push(run.alternatives(np.array([sid], dtype=np.int64)))
                    continue
                batch.append(sid)
                popped.append(sid)
                if final:  # checked now, accepted only once nothing pending can beat it
                    finals.append(entry)
                    continue
                if len(popped) == 1 and spec_len:
                    length = max(1, round(min(spec_len, W - 1) * spec_rate))
                    chain = run.speculate(sid, length)
                    chain_ids = chain[0]
                    push(chain)
                    batch.extend(chain[0].tolist())
            if not batch:
                continue
            run.check(np.array(batch, dtype=np.int64))
            if chain_ids.size:  # shorter lookahead where the way ahead keeps being blocked
                passed = float(np.mean(run.status[chain_ids] == 1)) * float(run.status[popped[0]] == 1)
                spec_rate = 0.5 * spec_rate + 0.5 * passed
                chain_ids = _NO_IDS
            # the popped states now (the chains wait in the heap for their turn)
            expand: list[int] = []
            failed: list[int] = []
            for k, sid in enumerate(popped):
                if run.status[sid] != 1:
                    failed.append(sid)
                    continue
                node = int(run.node[sid])
                t = float(run.t[sid])
                if t >= AT[node] - _EPS_T:
                    continue
                if node == goal_i or t >= stop:
                    if k == 0:  # popped first: nothing in this batch can reach its node sooner
                        accept(sid, t, node)
                        return run.reconstruct(sid), expanded, "ok"
                    continue  # back to the heap below, checked
                if accept(sid, t, node):
                    return run.reconstruct(sid), expanded, "ok"
                expand.append(sid)
            for entry in finals:
                if run.status[entry[2]] == 1 and entry[2] != popped[0]:
                    heapq.heappush(heap, entry)
            if failed:
                push(run.alternatives(np.array(failed, dtype=np.int64)))
            if expand:
                push(run.children(np.array(expand, dtype=np.int64)))
            if not probed and expanded >= cfg.probe_after_expansions and goal is not None:
                probed = True
                t_probe = max(t_static, t_start)
                longest = self._approach_probe(sep, goal, t_probe, hold_s, run.t_last)
                if longest is not None:  # no way into the goal once the person holds still
                    blocked_from = t_probe
                    run.t_nongoal = min(run.t_nongoal, t_probe)
                    run.t_last = min(run.t_last, t_probe + longest)
                    run.h_pred = self._to_goal_neighbours(goal)
        return _exhausted(goal, t_last, t_start, cfg.max_plan_s, expanded, blocked_from)

    def _search_compiled(
        self,
        run: _Run,
        t_start: float,
        sep: _Separation,
        *,
        goal: int | None,
        hold_s: float,
        W: int,
        deadline: float | None,
    ) -> tuple[Plan | None, int, str]:
        """The loop of :meth:`_search` over the compiled open list (:class:`_OpenList`): the same states
        popped, checked and accepted in the same order (the pop loop runs in
        :func:`app.planning._kernels.pop_batch` up to each step that needs Python), the same result."""
        cfg = self.config
        t_last = run.t_last
        AT = run.AT
        ol = _OpenList(run)
        ol.push(run.start_moves())
        goal_i = -2 if goal is None else goal
        stop = math.inf if run.stop_time is None else run.stop_time
        spec_len = W // 2 if goal is not None and W > 1 else 0
        n_batches = 0
        spec_rate = 1.0
        chain_ids = _NO_IDS
        expanded = 0
        probed = goal is None or sep.forecast is None
        t_static = sep.t_static
        blocked_from: float | None = None
        ctx = np.array([goal_i, stop, 0.0, run.t_nongoal, run.t_last, cfg.heuristic_weight])
        h_pred = np.zeros((0, NUM_BRANCHES))
        out = np.empty((2, W), dtype=np.int64)

        def accept(sid: int, t: float, node: int) -> bool:
            nonlocal expanded
            AT[node] = t
            run.accepted[sid] = True
            expanded += 1
            if node == goal_i or t >= stop:
                return True
            if ol.def_head[sid] >= 0:
                ol.release(sid)
            return False

        while ol.hs[0]:
            if deadline is not None and self._timer() > deadline:
                return None, expanded, "deadline"
            if expanded >= cfg.max_expansions:
                return None, expanded, f"no plan within {cfg.max_expansions} expansions"
            batch: list[int] = []
            popped: list[int] = []
            finals: list[int] = []  # entries
            n_batches += 1
            W_b = min(W, 8 + 4 * n_batches)
            while True:
                code, n_out, e, n_fin = _kernels.pop_batch(
                    ol.heap, ol.hs, ol.E_key, ol.E_negt, ol.E_id, ol.def_head, ol.def_next, AT, run._I,
                    run._B, run.status, ctx, h_pred, len(batch), W_b, len(popped), spec_len > 0, out,
                )  # fmt: skip
                E_id = ol.E_id
                if n_out:
                    got = out[0, :n_out].tolist()
                    batch.extend(got)
                    popped.extend(got)
                    if n_fin:
                        finals.extend(out[1, :n_fin].tolist())
                if code == _kernels.POP_SPECULATE:
                    length = max(1, round(min(spec_len, W - 1) * spec_rate))
                    chain = run.speculate(popped[0], length)
                    chain_ids = chain[0]
                    ol.push(chain)
                    batch.extend(chain[0].tolist())
                elif code == _kernels.POP_ACCEPT:
                    sid = int(E_id[e])
                    if accept(sid, -float(ol.E_negt[e]), int(run.node[sid])):
                        return run.reconstruct(sid), expanded, "ok"
                    ol.push(run.children(np.array([sid], dtype=np.int64)))
                elif code == _kernels.POP_ALTERNATIVES:
                    ol.push(run.alternatives(np.array([E_id[e]], dtype=np.int64)))
                else:
                    break
            if not batch:
                continue
            run.check(np.array(batch, dtype=np.int64))
            if chain_ids.size:
                n_pass = int(np.count_nonzero(run.status[chain_ids] == 1))
                passed = n_pass / chain_ids.size * float(run.status[popped[0]] == 1)
                spec_rate = 0.5 * spec_rate + 0.5 * passed
                chain_ids = _NO_IDS
            n_acc, failed, expand, final_sid = _kernels.accept_checked(
                np.array(popped, dtype=np.int64), run.status, run._F, run._I, run._B, AT, goal_i, stop,
                ol.def_head, ol.def_next, ol.heap, ol.hs, ol.E_key, ol.E_negt, ol.E_id,
            )  # fmt: skip
            expanded += n_acc
            if final_sid >= 0:
                return run.reconstruct(int(final_sid)), expanded, "ok"
            for ek in finals:
                if run.status[ol.E_id[ek]] == 1 and ol.E_id[ek] != popped[0]:
                    ol.push_back(ek)
            if failed.size:
                ol.push(run.alternatives(failed))
            if expand.size:
                ol.push(run.children(expand))
            if not probed and expanded >= cfg.probe_after_expansions and goal is not None:
                probed = True
                t_probe = max(t_static, t_start)
                longest = self._approach_probe(sep, goal, t_probe, hold_s, run.t_last)
                if longest is not None:
                    blocked_from = t_probe
                    run.t_nongoal = min(run.t_nongoal, t_probe)
                    run.t_last = min(run.t_last, t_probe + longest)
                    run.h_pred = self._to_goal_neighbours(goal)
                    h_pred = _kernels.as_f64(run.h_pred)
                    ctx[2:5] = (1.0, run.t_nongoal, run.t_last)
        return _exhausted(goal, t_last, t_start, cfg.max_plan_s, expanded, blocked_from)

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
        # usually some branch is free once the person holds still: then nothing more to find out
        last = sep.check(
            self._ik[goal, branches],
            np.full(nb, ts[-1]),
            np.zeros(nb),
            self._cen_all[goal, branches],
            self._rad_all[goal, branches],
        )
        if np.any(last):
            return math.inf
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

    def _approach_probe(
        self, sep: _Separation, goal: int, t_static: float, hold_s: float, t_last: float
    ) -> float | None:
        """Whether the goal can still be entered once the forecast has come to rest (``t_static``).

        Checks every move the search could make into the goal (each roadmap neighbour, each valid branch
        there, the ``max_branch_tries`` nearest goal branches) the slowest way the search makes it (the
        nearest branch at the slowest of ``slow_speed_fractions``, the others at the cruise speed), from
        rest, with the goal hold, departing at ``t_static``. From then on the person and the margin no
        longer change, and a faster move needs at least as much separation at every point of its path, so
        when even these fail no move into the goal that departs later passes. Moves that could not arrive
        by ``t_last`` (the search's bound) are left out. Returns None when some move passes, else the
        longest of the moves (s): a plan must then arrive within that long after ``t_static``.
        """
        rm = self.roadmap
        entries = np.flatnonzero(rm.indices == goal)
        if entries.size == 0:
            return None
        src = np.searchsorted(rm.indptr, entries, side="right") - 1
        e = np.repeat(entries, NUM_BRANCHES * self._R)
        u = np.repeat(src, NUM_BRANCHES * self._R)
        bu = np.tile(np.repeat(np.arange(NUM_BRANCHES), self._R), entries.size)
        k = np.tile(np.arange(self._R), entries.size * NUM_BRANCHES)
        row = e * NUM_BRANCHES + bu
        L = self._L_flat[row, k]
        keep = np.isfinite(L) & self._valid[u, bu]
        if not keep.any():
            return None
        u, bu, row, k, L = u[keep], bu[keep], row[keep], k[keep], L[keep]
        b = self._ord_flat[row, k]
        q_a = self._ik[u, bu]
        target = self._align(self._ik[goal, b], q_a)
        m = u.size
        # the slowest move the search makes there: the nearest branch at the slowest speed, the others at
        # the cruise speed (it tries no other branch slower); from rest, slower than any entry speed
        f_min = min((self.config.speed_fraction, *self.config.slow_speed_fractions))
        f = np.where(k == 0, f_min, self.config.speed_fraction)
        end = np.ones(m, dtype=bool)
        h, _, _ = _profile_arrays(np.zeros(m), L, f, self._A, end)
        h = np.where(L > 1e-12, np.maximum(h, self.config.min_edge_s), h)
        fits = t_static + h <= t_last
        if not fits.any():
            return 0.0
        u, bu, b, q_a, target, L, h, f = (x[fits] for x in (u, bu, b, q_a, target, L, h, f))
        m = u.size
        # the moves from the roomiest configurations first: one that passes ends the probe early
        assert sep.forecast is not None
        pose = sep._poses(np.full(m, t_static))
        room = self.collision.distance_to_human_paired(q_a, pose)
        order = np.argsort(-room, kind="stable")
        bounds = [0, 4, 16, *range(32, m, 32), m]
        for c0, c1 in itertools.pairwise(bounds):
            if c0 >= m:
                break
            i = order[c0:c1]
            n = i.size
            ones = np.ones(n, dtype=bool)
            ok = self._moves_ok(
                sep,
                q_a[i],
                self._pts_all[u[i], bu[i]],
                self._cen_all[u[i], bu[i]],
                self._rad_all[u[i], bu[i]],
                np.full(n, goal),
                b[i],
                target[i],
                np.full(n, t_static),
                h[i],
                np.zeros(n),
                L[i],
                ones,
                f[i],
                ones,
                hold_s,
            )
            if ok.any():
                return None
        return float(h.max())

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
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Check moves (and the hold at their end where ``hold``) against the forecast; boolean (M,).
        The arguments are those of :meth:`_move_samples`."""
        M = q_a.shape[0]
        result = np.ones(M, dtype=bool)
        if sep.forecast is None or M == 0:
            return result
        if sep._kernel is not None:
            return self._moves_ok_compiled(
                sep,
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
                f,
                hold,
                hold_s,
                target_geometry=target_geometry,
            )
        sel, owner, q, t, v, cen, rad = self._move_samples(
            sep,
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
            f,
            hold,
            hold_s,
            target_geometry=target_geometry,
        )
        if sel.size:
            ok_s = sep.check(q, t, v, cen, rad, owner)
            result[sel] = np.bincount(owner, weights=~ok_s, minlength=sel.size) == 0
        return result

    def _move_prep(
        self,
        q_a: np.ndarray,
        pts_a: np.ndarray,
        cv: np.ndarray,
        b: np.ndarray,
        target: np.ndarray,
        h: np.ndarray,
        u0: np.ndarray,
        L: np.ndarray,
        end_rest: np.ndarray,
        f: np.ndarray,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> tuple[np.ndarray, ...]:
        """Per move (arguments as in :meth:`_move_samples`): the joint step ``dq`` (M, 6), how far the
        joints can carry each capsule ``travel`` (M, L), the target's spheres ``cen_b`` (M, L, 3) / ``rad_b``
        (M, L), the profile's duration and peak speed, its clock (profile seconds per real second) and
        ``kv`` (m/s per unit of path speed)."""
        M = q_a.shape[0]
        dq = target - q_a
        cum = np.concatenate([np.zeros((M, 1)), np.cumsum(np.abs(dq) * self._lever, axis=1)], axis=1)
        travel = cum[:, self._moved_by]  # (M, L): how far joints 1..J(l) can carry capsule l
        if target_geometry is None:
            pts_b, cen_b, rad_b = self._pts_all[cv, b], self._cen_all[cv, b], self._rad_all[cv, b]
        else:
            pts_b, cen_b, rad_b = target_geometry
        chord = np.max(np.linalg.norm(pts_b - pts_a, axis=-1), axis=-1)
        dur, _, peak = _profile_arrays(u0, L, f, self._A, end_rest)
        moving = L > 1e-12
        clock = np.where(h > 0, dur / np.maximum(h, 1e-12), 1.0)  # profile seconds per real second
        # m/s per unit of path speed
        kv = np.where(moving, self.config.speed_factor * chord * clock / np.maximum(L, 1e-12), 0.0)
        return dq, travel, cen_b, rad_b, dur, peak, clock, kv

    def _moves_ok_compiled(
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
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """:meth:`_moves_ok` in one compiled pass (:func:`app.planning._kernels.moves_separation_ok`): the
        same stage 0, samples and exact distances (and the same :meth:`_move_prep`); a move stops at its
        first sample that fails."""
        f64, M = _kernels.as_f64, q_a.shape[0]
        if target_geometry is None:
            pts_tab, cen_tab, rad_tab = self._k_tables
            rows = _kernels.as_i64(np.asarray(cv) * NUM_BRANCHES + np.asarray(b))
        else:
            pts_tab, cen_tab, rad_tab = (f64(x) for x in target_geometry)
            rows = np.arange(M, dtype=np.int64)
        ok, n_samples, n_exact = _kernels.moves_separation_ok(
            f64(q_a),
            f64(target),
            f64(pts_a),
            f64(cen_a),
            f64(rad_a),
            pts_tab,
            cen_tab,
            rad_tab,
            rows,
            _per_move(t_dep, M),
            f64(h),
            f64(u0),
            f64(L),
            _per_move(f, M),
            _per_move(end_rest, M, np.bool_),
            _per_move(hold, M, np.bool_),
            self._k_lever,
            self._k_moved_by,
            self._k_speed_factor,
            self._A,
            self._k_sample_dt,
            float(hold_s),
            sep._k_offsets,
            sep._k_params,
            *sep._k_forecast,
            *sep._k_window,
            *sep._kernel,
        )
        sep.samples += n_samples
        sep.exact_samples += n_exact
        return ok

    def _move_samples(
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
        f: np.ndarray,
        hold: np.ndarray,
        hold_s: float,
        *,
        target_geometry: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, ...]:
        """The samples of the moves (and the holds at their end where ``hold``) that stage 0 cannot pass.

        Returns ``(sel (M',), owner (S,), q (S, 6), t (S,), v (S,), cen (S, L, 3), rad (S, L))``: the moves
        that need samples and, per sample, its move (index into ``sel``), configuration, time, robot speed
        (m/s) and the spheres that contain the robot's capsules. A move passes when all its samples pass.

        Per move: the start configuration ``q_a`` with its capsule points/spheres, the target roadmap node
        ``cv`` at branch ``b`` (configuration ``target``), departure, duration, entry speed (``<= f``),
        length, whether it ends at rest and its cruise speed ``f``. ``target_geometry``: the target's capsule
        points (M, 2L, 3), sphere centres (M, L, 3) and radii (M, L) when it is not a roadmap configuration
        (``cv``, ``b`` are then not used).

        The robot speed of a sample (for ``S_r + S_s``) is the largest speed the path-speed profile reaches
        between the previous sample and this one, turned into m/s with the move's largest chord (the
        furthest any capsule point travels between the two configurations) per unit of path, times
        ``speed_factor`` (arcs are longer than chords); the hold after a move is at rest.
        """
        M = q_a.shape[0]
        cfg = self.config
        A = self._A
        dq, travel, cen_b, rad_b, dur, peak, clock, kv = self._move_prep(
            q_a, pts_a, cv, b, target, h, u0, L, end_rest, f, target_geometry
        )
        # stage 0: moves far from the person over their whole time window pass without samples; a capsule
        # point is within frac * T of its start and (1 - frac) * T of its end, so within
        # T / 2 + (rho_a + rho_b) / 2 of the middle of the two sphere centres
        near = sep.near_moves(
            0.5 * (cen_a + cen_b),
            0.5 * (rad_a + rad_b + travel),
            t_dep,
            t_dep + h + np.where(hold, hold_s, 0.0),
            kv * peak,
        )
        sel = np.flatnonzero(near)
        if sel.size < M:
            q_a, cen_a, rad_a, cen_b, rad_b, t_dep, h, u0, L, end_rest, f, hold, dq, travel = (
                x[sel]
                for x in (q_a, cen_a, rad_a, cen_b, rad_b, t_dep, h, u0, L, end_rest, f, hold, dq, travel)
            )
            dur, clock, kv = dur[sel], clock[sel], kv[sel]
        M = sel.size
        # samples: the move every sample_dt_s (its end included), then the hold
        n = np.maximum(np.ceil(h / cfg.sample_dt_s - 1e-9), 1).astype(np.int64)
        n_hold_1 = max(math.ceil(hold_s / cfg.sample_dt_s - 1e-9), 0)
        tot = n + np.where(hold, n_hold_1, 0)
        owner = np.repeat(np.arange(M), tot)
        i = np.arange(owner.shape[0]) - np.repeat(np.cumsum(tot) - tot, tot) + 1
        n_o, h_o = n[owner], h[owner]
        in_move = i <= n_o
        tau = np.where(in_move, i / n_o, 1.0) * h_o
        c_o = clock[owner]
        frac, speed = _profile_samples(
            tau * c_o,
            np.where(in_move, i - 1, n_o) / n_o * h_o * c_o,
            u0[owner],
            L[owner],
            dur[owner],
            f[owner],
            A,
            end_rest[owner],
        )
        frac = np.where(in_move, frac, 1.0)
        q = q_a[owner] + frac[:, None] * dq[owner]
        t = t_dep[owner] + tau + np.where(in_move, 0.0, (i - n_o) * (hold_s / max(n_hold_1, 1)))
        v = np.where(in_move, kv[owner] * speed, 0.0)
        # capsule l lies within its start sphere grown by frac * T_l and its end sphere grown by
        # (1 - frac) * T_l; take the smaller sphere
        fo = frac[:, None]
        tr = travel[owner]
        ra = rad_a[owner] + fo * tr
        rb = rad_b[owner] + (1.0 - fo) * tr
        use_a = ra <= rb
        cen = np.where(use_a[..., None], cen_a[owner], cen_b[owner])
        rad = np.where(use_a, ra, rb)
        return sel, owner, q, t, v, cen, rad


class _Run:
    """The records of one search: every generated state in growable numpy arrays (one row per state).

    Owned by one query (never shared, never written to the roadmap). A state is a move from a parent state
    to a roadmap node at an IK branch: departure, duration, entry/exit path speed, cruise speed, the
    alternative it is (0 = nearest branch at cruise speed; others are generated when it fails) and the row of
    the option table it came from (its successor branches, for the alternatives). Row 0 is the start.
    Generation, timing and checking work on whole arrays of states at once.
    """

    _FLOAT = ("t", "u", "u0", "dep", "fc", "L", "h", "peak", "wait_ok")
    _INT = ("node", "branch", "parent", "row", "spec_child")
    _BOOL = ("end", "same", "accepted", "qset")

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
        h_tab: np.ndarray | None,
        t_last: float,
    ) -> None:
        self.p = planner
        self.sep = sep
        self.goal = goal
        self.stop_time = stop_time
        self.hold_s = hold_s
        self.h_tab = h_tab
        self.t_last = t_last
        self.t_nongoal = math.inf  # states at other nodes than the goal must arrive before this (s)
        self.h_pred: np.ndarray | None = None  # (N, 8) time lower bound to a roadmap neighbour of the goal
        cfg = planner.config
        self.f = cfg.speed_fraction
        self.A = planner._A
        self.min_edge = cfg.min_edge_s
        self.w_h = cfg.heuristic_weight
        self.AT = np.full(planner.roadmap.num_nodes, np.inf)
        cap = 256
        # the records, packed: one row per field (the attributes named in _FLOAT/_INT/_BOOL are views)
        self._F = np.zeros((len(self._FLOAT), cap))
        self._I = np.full((len(self._INT), cap), -1, dtype=np.int64)
        self._B = np.zeros((len(self._BOOL), cap), dtype=bool)
        self._bind()
        self.alt = np.zeros(cap, dtype=np.int8)
        self.status = np.zeros(cap, dtype=np.int8)  # check result: 0 not yet, 1 passed, 2 failed
        self.q = np.empty((cap, 6))  # the configuration once checked (or precomputed: ``qset``)
        self.n = 1
        self.t[0] = self.dep[0] = t_start
        self.fc[0] = self.f
        self.same[0] = self.accepted[0] = self.qset[0] = True
        self.status[0] = 1
        self.next_rows = None if goal is None else planner._next_cache.get(goal)
        # the compiled bookkeeping (with the compiled model; the NumPy code below is its reference)
        self.compiled = planner._k_align is not None and planner._kernel_geometry is not None
        self._h_tab_k = _kernels.as_f64(h_tab) if h_tab is not None else np.zeros((0, NUM_BRANCHES))
        self._kinds: np.ndarray | None = None
        self._ctx_key: tuple[float, float, bool] | None = None
        self._ctx: tuple[np.ndarray, np.ndarray] = (np.zeros(8), np.zeros((0, NUM_BRANCHES)))
        self.wait_ok[:] = np.nan  # per checked state: until when standing still there is safe (NaN: unknown)
        self.q[0] = q_start
        pts, cen, rad = planner._points_and_spheres(q_start[None])
        self.start_pts, self.start_cen, self.start_rad = pts[0], cen[0], rad[0]
        self._start_k = tuple(_kernels.as_f64(x) for x in (pts[0], cen[0], rad[0]))
        # option tables: rows e * 8 + b of the planner's edge tables, then the start's rows (-1 - j)
        self.start_b = np.zeros((1, planner._R), dtype=np.int64)
        self.start_L = np.full((1, planner._R), np.inf)

    # -- records
    def _grow(self, m: int) -> None:
        cap = self.t.shape[0]
        if self.n + m <= cap:
            return
        new = max(2 * cap, self.n + m)
        F = np.zeros((len(self._FLOAT), new))
        F[:, :cap] = self._F
        F[_kernels.REC_WAIT_OK, cap:] = np.nan
        I = np.full((len(self._INT), new), -1, dtype=np.int64)  # noqa: E741
        I[:, :cap] = self._I
        B = np.zeros((len(self._BOOL), new), dtype=bool)
        B[:, :cap] = self._B
        self._F, self._I, self._B = F, I, B
        self._bind()
        for name in ("alt", "status", "q"):
            old = getattr(self, name)
            arr = np.zeros((new, *old.shape[1:]), dtype=old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def _bind(self) -> None:
        """The record attributes as views of the packed arrays."""
        for group, names in ((self._F, self._FLOAT), (self._I, self._INT), (self._B, self._BOOL)):
            for k, name in enumerate(names):
                setattr(self, name, group[k])

    def _options(self, row: np.ndarray, k: int | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Branch, length and roadmap-checked flag of option ``k`` of each option-table row."""
        p = self.p
        glob = row >= 0
        if glob.all():
            return p._ord_flat[row, k], p._L_flat[row, k], p._same_flat[row, k]
        g = np.where(glob, row, 0)
        s = np.where(glob, 0, -1 - row)
        b = np.where(glob, p._ord_flat[g, k], self.start_b[s, k])
        L = np.where(glob, p._L_flat[g, k], self.start_L[s, k])
        return b, L, glob & p._same_flat[g, k]

    def moves(
        self,
        parent: np.ndarray,
        node: np.ndarray,
        branch: np.ndarray,
        L: np.ndarray,
        same: np.ndarray,
        t_dep: np.ndarray,
        u0: np.ndarray,
        fc: np.ndarray | float,
        alt: int | np.ndarray,
        row: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Time moves (arrays of one entry per move), keep those that could improve their node's arrival
        and pass the prune, and record them. Returns (state ids, keys t + w h, arrival times)."""
        fin = np.isfinite(L)
        if not fin.all():
            parent, node, branch, L, same, t_dep, u0, row = (
                x[fin] for x in (parent, node, branch, L, same, t_dep, u0, row)
            )
            if isinstance(fc, np.ndarray):
                fc = fc[fin]
            if isinstance(alt, np.ndarray):
                alt = alt[fin]
        m = parent.shape[0]
        fc = np.broadcast_to(np.asarray(fc, dtype=np.float64), (m,))
        end = node == self.goal if self.goal is not None else np.zeros(m, dtype=bool)
        u0 = np.minimum(u0, fc)
        h, u1, peak = _profile_arrays(u0, L, fc, self.A, end)
        h = np.where(L > 1e-12, np.maximum(h, self.min_edge), h)
        ta = t_dep + h
        w = self.w_h
        if self.h_tab is not None:
            hv = self.h_tab[node, branch]
        elif self.stop_time is not None:
            hv, w = np.maximum(self.stop_time - ta, 0.0), 1.0
        else:
            hv = np.zeros(m)
        # an admissible prune: with a weight w > 1 the key t + w h >= t + h, so compare t + h itself
        keep = (ta < self.AT[node] - _EPS_T) & (ta + hv <= self.t_last)
        if self.t_nongoal < math.inf:
            h_pred = self.h_pred[node, branch] if self.h_pred is not None else 0.0
            keep &= (node == self.goal) | (ta + h_pred < self.t_nongoal)
        if not keep.all():
            idx = np.flatnonzero(keep)
            parent, node, branch, L, same, t_dep, u0, row, fc, end, h, u1, peak, ta, hv = (
                x[idx] for x in (parent, node, branch, L, same, t_dep, u0, row, fc, end, h, u1, peak, ta, hv)
            )
            m = idx.size
            if isinstance(alt, np.ndarray):
                alt = alt[idx]
        self._grow(m)
        ids = np.arange(self.n, self.n + m)
        self.n += m
        self.node[ids] = node
        self.branch[ids] = branch
        self.parent[ids] = parent
        self.t[ids] = ta
        self.u[ids] = u1
        self.u0[ids] = u0
        self.dep[ids] = t_dep
        self.fc[ids] = fc
        self.L[ids] = L
        self.h[ids] = h
        self.peak[ids] = peak
        self.end[ids] = end
        self.same[ids] = same
        self.alt[ids] = alt
        self.row[ids] = row
        return ids, ta + w * hv, ta

    # -- generation
    def start_moves(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moves from the start to its nearest roadmap nodes (each checked against the scene when popped)."""
        p = self.p
        q = self.q[0]
        # a robot at rest at a task pose is common: try the stations before the whole roadmap
        st = p._station_array
        Ls = np.where(p._valid[st], p._metric(p._align(p._ik[st], q[None, None, :]) - q), np.inf)
        hit = np.flatnonzero(Ls.min(axis=1) <= 1e-9)
        if hit.size and int(st[hit[0]]) != self.goal:
            n = int(st[hit[0]])
            self.node[0], self.branch[0] = n, int(np.argmin(Ls[hit[0]]))
            self.AT[n] = self.t[0]
            return self.children(np.zeros(1, dtype=np.int64))
        aligned = p._align(p._ik, q[None, None, :])
        L = np.where(p._valid, p._metric(aligned - q), np.inf)
        best = L.min(axis=1)
        k = min(p.config.start_neighbors, int(np.isfinite(best).sum()))
        if k == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        nodes = np.argpartition(best, k - 1)[:k]
        at_node = nodes[best[nodes] <= 1e-9]
        if at_node.size:  # the start is a roadmap configuration: the roadmap's edges take it from there
            nodes, k = at_node[:1], 1
            n = int(nodes[0])
            if n != self.goal:  # the start state is that node (statically free, checked against the person)
                self.node[0], self.branch[0] = n, int(np.argmin(L[n]))
                self.AT[n] = self.t[0]
                return self.children(np.zeros(1, dtype=np.int64))
        order = np.argsort(L[nodes], axis=1, kind="stable")[:, : p._R]
        self.start_b = order.astype(np.int64)
        self.start_L = np.take_along_axis(L[nodes], order, axis=1)
        row = -1 - np.arange(k)
        zeros = np.zeros(k)
        return self.moves(
            np.zeros(k, dtype=np.int64),
            nodes.astype(np.int64),
            self.start_b[:, 0],
            self.start_L[:, 0],
            np.zeros(k, dtype=bool),
            zeros + self.t[0],
            zeros,
            self.f,
            0,
            row,
        )

    def _context(self) -> tuple[np.ndarray, np.ndarray]:
        """The compiled generation's scalars (see :func:`app.planning._kernels.children_moves`) and
        ``h_pred`` ((0, 8) where there is none)."""
        key = (self.t_last, self.t_nongoal, self.h_pred is None)
        if self._ctx_key != key:  # the prune's bounds change only after the approach probe
            goal = -2 if self.goal is None else self.goal
            stop = math.nan if self.stop_time is None else self.stop_time
            ctx = np.array([goal, self.A, self.min_edge, self.w_h, stop, self.t_last, self.t_nongoal, self.f])
            h_pred = self.h_pred if self.h_pred is not None else np.zeros((0, NUM_BRANCHES))
            self._ctx = (ctx, _kernels.as_f64(h_pred))
            self._ctx_key = key
        return self._ctx

    def _recorded(
        self, n: int, keys: np.ndarray, ta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ids = np.arange(self.n, n)
        self.n = n
        return ids, keys, ta

    def children(self, sids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moves from checked states to all their roadmap neighbours (nearest branch, cruise speed)."""
        p = self.p
        if self.compiled:
            self._grow(p._max_degree * sids.size)
            ctx, h_pred = self._context()
            return self._recorded(
                *_kernels.children_moves(
                    sids, p._k_indptr, p._k_indices, p._ord_flat, p._L_flat, p._same_flat, self.f,
                    NUM_BRANCHES, ctx, self._h_tab_k, h_pred, self.AT, self._F, self._I, self._B, self.alt,
                    self.n,
                )
            )  # fmt: skip
        u, bu = self.node[sids], self.branch[sids]
        a, z = p._indptr[u], p._indptr[u + 1]
        cnt = z - a
        owner = np.repeat(np.arange(sids.size), cnt)
        e = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt - a, cnt)
        row = e * NUM_BRANCHES + bu[owner]
        par = sids[owner]
        spec = self.spec_child[par]
        has = spec >= 0
        if has.any():  # the speculative chain already holds that move
            keep = ~has | (p._indices[e] != self.node[np.maximum(spec, 0)])
            e, row, par = e[keep], row[keep], par[keep]
        return self.moves(
            par,
            p._indices[e],
            p._ord_flat[row, 0],
            p._L_flat[row, 0],
            p._same_flat[row, 0],
            self.t[par],
            self.u[par],
            self.f,
            0,
            row,
        )

    def speculate(self, sid: int, max_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A chain of moves ahead of the unchecked state ``sid`` along the static shortest path (nearest
        branch, cruise speed: the moves a search would try first), to be checked in the same batch as
        ``sid`` (lookahead: when the way is clear, one batch checks the whole rest of the path).

        The chain's states are ordinary states (timed like children, pushed with their keys); their parent
        must still be accepted before they are. Stops at the goal, at a node already reached no later, at
        the prune, after ``max_len`` moves.
        """
        nxt = self.next_rows
        if nxt is None or max_len <= 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        p = self.p
        if self.compiled:
            self._grow(max_len)
            ctx, h_pred = self._context()
            return self._recorded(
                *_kernels.speculate_chain(
                    sid, max_len, p._next_cache_k[self.goal], p._k_indices, p._ord_flat, p._L_flat,
                    p._same_flat, p._delta0, p._k_ik, p._k_q_lo, p._k_q_hi, ctx,
                    self._h_tab_k, h_pred, self.AT, self._F, self._I, self._B, self.alt, self.q, self.n,
                )
            )  # fmt: skip
        node, b = int(self.node[sid]), int(self.branch[sid])
        par = int(self.parent[sid])
        q_prev = p._align(p._ik[node, b], self.q[par]) if not self.qset[sid] else self.q[sid]
        self.q[sid] = q_prev
        self.qset[sid] = True
        t, u = float(self.t[sid]), float(self.u[sid])
        f, A, goal, AT, h_tab = self.f, self.A, self.goal, self.AT, self.h_tab
        assert h_tab is not None
        chain: list[tuple[int, int, int, float, bool, float, float, float, float, float]] = []
        qs = []
        while len(chain) < max_len and node != goal:
            row = nxt[node * NUM_BRANCHES + b]
            if row < 0:
                break
            v = p._indices_list[row // NUM_BRANCHES]
            bv = p._ord_list[row]
            L = p._L_list[row]
            end = v == goal
            h, u1, peak = _profile_py(u, L, f, A, end)
            if L > 1e-12:
                h = max(h, self.min_edge)
            ta = t + h
            hv = float(h_tab[v, bv])
            if ta >= AT[v] - _EPS_T or ta + hv > self.t_last:
                break
            if v != goal and ta + (0.0 if self.h_pred is None else self.h_pred[v, bv]) >= self.t_nongoal:
                break
            q_next = q_prev + p._delta0[row]  # the nearest 2 pi shift, as _align finds it within the limits
            if not np.all((q_next >= p.q_min) & (q_next <= p.q_max)):
                q_next = p._align(p._ik[v, bv], q_prev)
            q_prev = q_next
            qs.append(q_prev)
            chain.append((row, v, bv, L, p._same_list[row], t, min(u, f), h, u1, peak))
            node, b, t, u = v, bv, ta, u1
        m = len(chain)
        if m == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        self._grow(m)
        ids = np.arange(self.n, self.n + m)
        self.n += m
        cols = list(zip(*chain, strict=True))
        self.row[ids] = cols[0]
        self.node[ids] = cols[1]
        self.branch[ids] = cols[2]
        self.L[ids] = cols[3]
        self.same[ids] = cols[4]
        self.dep[ids] = cols[5]
        self.u0[ids] = cols[6]
        self.h[ids] = cols[7]
        self.u[ids] = cols[8]
        self.peak[ids] = cols[9]
        self.t[ids] = self.dep[ids] + self.h[ids]
        self.parent[ids] = np.concatenate([[sid], ids[:-1]])
        self.spec_child[self.parent[ids]] = ids
        self.fc[ids] = f
        self.end[ids] = self.node[ids] == goal
        self.alt[ids] = 0
        self.q[ids] = qs
        self.qset[ids] = True
        ta = self.t[ids]
        return ids, ta + self.w_h * h_tab[self.node[ids], self.branch[ids]], ta

    def alternatives(self, failed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """When the nearest branch at cruise speed fails: the next branches (alternative 1), the nearest one
        slower (2), after waiting (3), after stopping at the slowest speed (4)."""
        cfg = self.p.config
        if self.compiled:
            if self._kinds is None:
                self._kinds = np.array(self._alternative_kinds(), dtype=np.float64).reshape(-1, 4)
            p = self.p
            self._grow(failed.size * self._kinds.shape[0])
            ctx, h_pred = self._context()
            return self._recorded(
                *_kernels.alternative_moves(
                    failed, self._kinds, _NO_ROW, float(cfg.wait_step_s), float(self.sep.t_static),
                    self.start_b, _kernels.as_f64(self.start_L), p._ord_flat, p._L_flat, p._same_flat,
                    ctx, self._h_tab_k, h_pred, self.AT, self._F, self._I, self._B, self.alt, self.n,
                )
            )  # fmt: skip
        failed = failed[(self.alt[failed] == 0) & (self.row[failed] != _NO_ROW)]
        if failed.size == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        par, node, row = self.parent[failed], self.node[failed], self.row[failed]
        t, u = self.t[par], self.u[par]
        n = failed.size
        kinds = self._alternative_kinds()
        if not kinds:
            return np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
        spec = np.array(kinds, dtype=np.float64)  # (A, 4)
        a = spec.shape[0]
        alt = np.repeat(spec[:, 0].astype(np.int8), n)
        opt = np.repeat(spec[:, 1].astype(np.int64), n)
        fc = np.repeat(spec[:, 2], n)
        wait = np.repeat(spec[:, 3], n)
        par_r, node_r, row_r = np.tile(par, a), np.tile(node, a), np.tile(row, a)
        t_r = np.tile(t, a)
        # once the person holds still, waiting longer changes nothing: of the waits that depart then, only
        # the first is kept
        t_s = self.sep.t_static
        keep = (wait <= 1) | (t_r + (wait - 1) * cfg.wait_step_s < t_s)
        if not keep.all():
            alt, opt, fc, wait, par_r, node_r, row_r, t_r = (
                x[keep] for x in (alt, opt, fc, wait, par_r, node_r, row_r, t_r)
            )
            u_r = np.tile(u, a)[keep]
        else:
            u_r = np.tile(u, a)
        b, L, same = self._options(row_r, opt)
        u0 = np.where(wait != 0, 0.0, np.minimum(u_r, fc))  # from rest after a wait or a stop
        t_dep = t_r + np.maximum(wait, 0.0) * cfg.wait_step_s
        return self.moves(par_r, node_r, b, L, same, t_dep, u0, fc, alt, row_r)

    def _alternative_kinds(self) -> list[tuple[int, int, float, int]]:
        """(kind, option, cruise speed, wait steps) of each alternative of a failed move, in order."""
        cfg = self.p.config
        kinds = [(1, k, self.f, 0) for k in range(1, self.p._R)]
        if self.sep.forecast is not None:
            slow = [fs for fs in cfg.slow_speed_fractions if fs < self.f]
            kinds += [(2, 0, fs, 0) for fs in slow]
            if slow:  # stop, then creep (slower than creeping on at the parent's speed)
                kinds.append((4, 0, min(slow), -1))
            K, _ = _wait_grid(cfg)
            kinds += [(3, 0, self.f, k) for k in range(1, K + 1)]
        return kinds

    # -- checking (vectorised)
    def check(self, batch: np.ndarray) -> np.ndarray:
        """Check a batch of moves; stores the configuration of every move that passes. Returns (M,) bool."""
        if self.compiled:
            return self._check_fast(batch)
        p = self.p
        par = self.parent[batch]
        cv = self.node[batch]
        b = self.branch[batch]
        q_par = self.q[par]
        target = p._align(p._ik[cv, b], q_par)
        pre = self.qset[batch]
        if pre.any():  # a speculative chain: its configurations were aligned one after the other
            target[pre] = self.q[batch[pre]]
        ok = np.ones(batch.size, dtype=bool)
        # static scene: moves the roadmap checked (same branch, edge bit, the same move) need nothing more
        same = self.same[batch].copy()
        pn = self.node[par]
        pb = self.branch[par]
        chk = np.flatnonzero(same)
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
                    batch[live], par[live], cv[live], b[live], q_par[live], target[live]
                )
        good = batch[ok]
        self.q[good] = target[ok]
        self.status[batch] = np.where(ok, 1, 2)
        return ok

    def _check_fast(self, batch: np.ndarray) -> np.ndarray:
        """:meth:`check` with the compiled set-up (:func:`app.planning._kernels.check_prepare`) and the
        compiled move check called directly: the same checks in the same order, the same result."""
        p = self.p
        sep = self.sep
        target, same, q_par, pts, cen, rad, fl, hold, end, waits, rows, par, stored = _kernels.check_prepare(
            batch, self._F, self._I, self._B, self.q, p._k_ik, p._k_q_lo, p._k_q_hi, *p._k_tables,
            self._start_k[0], self._start_k[1], self._start_k[2],
            -2 if self.goal is None else self.goal, self.hold_s > 0,
        )  # fmt: skip
        M = batch.size
        target_all = target
        ok = np.ones(M, dtype=bool)
        if not same.all():
            todo = np.flatnonzero(~same)
            pt, st = par[todo], batch[todo]
            res = p._static_cached(
                self.node[pt], self.branch[pt], self.node[st], self.branch[st], q_par[todo], target[todo],
                same_move=stored[todo],
            )  # fmt: skip
            ok[todo] = res == 1
        if sep.forecast is not None:
            dep = fl[0]
            # waits: the parent must be able to stand still until the departure (checked once per parent)
            waits &= ok
            if waits.any():
                waiting = np.flatnonzero(waits)
                wp = par[waiting]
                wt = np.unique(wp[np.isnan(self.wait_ok[wp])])
                if wt.size:
                    self._check_waits(wt)
                ok[waiting] = dep[waiting] < self.wait_ok[wp] - _EPS_T
            live = None if ok.all() else np.flatnonzero(ok)
            if live is None or live.size:
                if live is not None:
                    q_par, target, pts, cen, rad, hold, end, rows = (
                        q_par[live], target[live], pts[live], cen[live], rad[live], hold[live], end[live],
                        rows[live],
                    )  # fmt: skip
                    fl = np.ascontiguousarray(fl[:, live])
                res, n_samples, n_exact = _kernels.moves_separation_ok(
                    q_par, target, pts, cen, rad, *p._k_tables, rows,
                    fl[0], fl[1], fl[2], fl[3], fl[4], end, hold,
                    p._k_lever, p._k_moved_by, p._k_speed_factor, p._A, p._k_sample_dt, float(self.hold_s),
                    sep._k_offsets, sep._k_params, *sep._k_forecast, *sep._k_window, *sep._kernel,
                )  # fmt: skip
                sep.samples += n_samples
                sep.exact_samples += n_exact
                if live is None:
                    ok = res
                else:
                    ok[live] = res
        _kernels.check_store(batch, ok, target_all, self.q, self.status)
        return ok

    def _check_waits(self, todo: np.ndarray) -> None:
        """Until when standing still at each of the checked states ``todo`` is safe (``wait_ok``)."""
        cfg = self.p.config
        K, sub = _wait_grid(cfg)
        n_w = K * sub
        sep = self.sep
        if self.compiled and sep._kernel is not None:  # the samples and their requirement compiled
            p = self.p
            qs, t_all, req, cen, rad, ts = _kernels.wait_samples(
                todo, self._F, self._I, self.q, p._k_tables[1], p._k_tables[2], self._start_k[1],
                self._start_k[2], n_w, cfg.wait_step_s / sub, sep._k_offsets, sep._k_forecast[0],
                sep._k_window[0], sep._k_params,
            )  # fmt: skip
            ok, exact = _kernels.sample_separation_ok(
                qs, t_all, req, cen, rad, True, _NO_IDS, 0, *sep._k_forecast, *sep._kernel
            )
            sep.samples += t_all.size
            sep.exact_samples += exact
            _kernels.wait_finish(todo, ok, ts, self.wait_ok)
            return
        ts = self.t[todo][:, None] + (cfg.wait_step_s / sub) * np.arange(1, n_w + 1)
        rep = np.repeat(np.arange(todo.size), n_w)
        _, cen_w, rad_w = self._parent_geometry(todo)
        res_w = self.sep.check(self.q[todo][rep], ts.reshape(-1), np.zeros(rep.size), cen_w[rep], rad_w[rep])
        res_w = res_w.reshape(todo.size, -1)
        first_bad = ts[np.arange(todo.size), np.argmin(res_w, axis=1)]
        self.wait_ok[todo] = np.where(res_w.all(axis=1), np.inf, first_bad)

    def _parent_geometry(self, par: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = self.p
        pn = self.node[par]
        pb = self.branch[par]
        on = pn >= 0
        if on.all():
            return p._pts_all[pn, pb], p._cen_all[pn, pb], p._rad_all[pn, pb]
        pn, pb = pn.clip(0), pb.clip(0)
        pts = np.where(on[:, None, None], p._pts_all[pn, pb], self.start_pts[None])
        cen = np.where(on[:, None, None], p._cen_all[pn, pb], self.start_cen[None])
        rad = np.where(on[:, None], p._rad_all[pn, pb], self.start_rad[None])
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
        """Moves against the forecast, with the waits before them, in one vectorised check (the NumPy
        reference of :meth:`_check_fast`: a run is compiled whenever its planner's checks are)."""
        p = self.p
        cfg = p.config
        sep = self.sep
        ok = np.ones(idx.size, dtype=bool)
        # waits: the parent must be able to stand still until the departure (checked once per parent)
        dep = self.dep[idx]
        waiting = np.flatnonzero(dep > self.t[par] + _EPS_T)
        todo = np.zeros(0, dtype=np.int64)
        parts: list[tuple[np.ndarray, ...]] = []
        if waiting.size:
            wp = par[waiting]
            todo = np.unique(wp[np.isnan(self.wait_ok[wp])])
            if todo.size:
                K, sub = _wait_grid(cfg)
                n_w = K * sub
                ts = self.t[todo][:, None] + (cfg.wait_step_s / sub) * np.arange(1, n_w + 1)
                rep = np.repeat(np.arange(todo.size), n_w)
                _, cen_w, rad_w = self._parent_geometry(todo)
                parts.append((self.q[todo][rep], ts.reshape(-1), np.zeros(rep.size), cen_w[rep], rad_w[rep]))
        n_wait = parts[0][0].shape[0] if parts else 0
        pts, cen, rad = self._parent_geometry(par)
        hold = cv == self.goal if self.goal is not None else np.full(idx.size, self.hold_s > 0)
        sel, owner, *samples = p._move_samples(
            sep,
            q_par,
            pts,
            cen,
            rad,
            cv,
            b,
            target,
            dep,
            self.h[idx],
            self.u0[idx],
            self.L[idx],
            self.end[idx],
            self.fc[idx],
            hold,
            self.hold_s,
        )
        parts.append(tuple(samples))
        # groups: every wait sample on its own (the first unsafe instant matters), then each move's samples
        groups = [np.arange(n_wait)] if n_wait else []
        groups.append(owner + n_wait)
        if len(parts) > 1:
            res = sep.check(*(np.concatenate(x) for x in zip(*parts, strict=True)), np.concatenate(groups))
        else:
            res = sep.check(*parts[0], groups[0])
        if todo.size:
            res_w = res[:n_wait].reshape(todo.size, -1)
            t_w = parts[0][1].reshape(todo.size, -1)
            first_bad = t_w[np.arange(todo.size), np.argmin(res_w, axis=1)]
            self.wait_ok[todo] = np.where(res_w.all(axis=1), np.inf, first_bad)
        if waiting.size:
            ok[waiting] = dep[waiting] < self.wait_ok[par[waiting]] - _EPS_T
        if sel.size:
            ok[sel] &= np.bincount(owner, weights=~res[n_wait:], minlength=sel.size) == 0
        return ok

    def reconstruct(self, sid: int) -> Plan:
        chain = []
        s = sid
        while s >= 0:
            chain.append(s)
            s = int(self.parent[s])
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
                    times.append(float(self.dep[s]))
                    qs.append(self.q[par])
                    nodes.append(int(self.node[par]))
            times.append(float(self.t[s]))
            qs.append(self.q[s])
            nodes.append(int(self.node[s]))
        return Plan(times=np.array(times), q=np.array(qs), nodes=np.array(nodes))


class _OpenList:
    """The compiled search's open list: entries ``(key, -t, state id)`` in an append-only table and a
    binary heap of entry indices (:mod:`app.planning._kernels`: ``heap_add``, ``pop_batch``), plus the
    entries that wait for a state to be accepted (linked lists: ``def_head`` per state, ``def_next`` per
    entry). Pops in exactly the order of ``heapq`` over the tuples."""

    def __init__(self, run: _Run) -> None:
        self.run = run
        cap = 1024
        self.E_key = np.zeros(cap)
        self.E_negt = np.zeros(cap)
        self.E_id = np.zeros(cap, dtype=np.int64)
        self.def_next = np.full(cap, -1, dtype=np.int64)
        self.heap = np.zeros(cap, dtype=np.int64)
        self.hs = np.zeros(2, dtype=np.int64)  # heap size, entries
        self.def_head = np.full(run.t.shape[0], -1, dtype=np.int64)

    def push(self, got: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        ids, keys, ts = got
        m = ids.shape[0]
        cap = self.E_key.shape[0]
        if self.hs[1] + m > cap:
            new = max(2 * cap, int(self.hs[1]) + m)
            for name in ("E_key", "E_negt", "E_id", "def_next", "heap"):
                old = getattr(self, name)
                arr = (
                    np.full(new, -1, dtype=old.dtype)
                    if name == "def_next"
                    else np.zeros(new, dtype=old.dtype)
                )
                arr[:cap] = old
                setattr(self, name, arr)
        n_states = self.run.t.shape[0]
        if self.def_head.shape[0] < n_states:
            head = np.full(n_states, -1, dtype=np.int64)
            head[: self.def_head.shape[0]] = self.def_head
            self.def_head = head
        if m:  # (the generation kernels' own arrays: int64 / float64, contiguous)
            _kernels.heap_add(ids, keys, ts, self.heap, self.hs, self.E_key, self.E_negt, self.E_id)

    def push_back(self, e: int) -> None:
        _kernels.heap_push(e, self.heap, self.hs, self.E_key, self.E_negt, self.E_id)

    def release(self, sid: int) -> None:
        _kernels.release_deferred(
            sid, self.def_head, self.def_next, self.heap, self.hs, self.E_key, self.E_negt, self.E_id
        )


def _exhausted(
    goal: int | None,
    t_last: float,
    t_start: float,
    max_plan_s: float,
    expanded: int,
    blocked_from: float | None,
) -> tuple[None, int, str]:
    """The result of a search whose open list ran empty."""
    if goal is not None and t_last < t_start + max_plan_s and not expanded:
        if t_last < t_start:
            return None, expanded, "goal blocked by the person for good"
        return None, expanded, f"goal blocked by the person from t={t_last - t_start:+.2f} s on"
    what = "goal" if goal is not None else "the emergency horizon"
    if blocked_from is not None:
        return (
            None,
            expanded,
            f"goal unreachable: every way into it is blocked once the person holds still "
            f"(t={blocked_from - t_start:+.2f} s), no safe path arrives before ({expanded} expansions)",
        )
    return None, expanded, f"{what} unreachable: no safe path found after {expanded} expansions"


_NO_IDS = np.zeros(0, dtype=np.int64)
_NO_ROW = -(2**62)  # option-table row of the start state (it has no alternatives)


def _per_move(x: np.ndarray | float | bool, m: int, dtype: type = np.float64) -> np.ndarray:
    """A per-move argument of the compiled checks: (m,) contiguous and writeable, broadcast if scalar."""
    if isinstance(x, np.ndarray) and x.shape == (m,) and x.dtype == dtype and x.flags.c_contiguous:
        return _kernels.as_bool(x) if dtype is np.bool_ else _kernels.as_f64(x)
    return np.array(np.broadcast_to(np.asarray(x, dtype=dtype), (m,)), order="C")


def _wait_grid(cfg: PlannerConfig) -> tuple[int, int]:
    """The waits of a search: how many ``wait_step_s`` steps fit in ``max_wait_s`` (``K``), and into how
    many samples each step is cut so that none is longer than ``sample_dt_s`` (``sub``)."""
    K = math.floor(cfg.max_wait_s / cfg.wait_step_s + 1e-9)
    sub = max(1, math.ceil(cfg.wait_step_s / cfg.sample_dt_s - 1e-9))
    return K, sub


def _profile_arrays(
    u0: np.ndarray, L: np.ndarray, f: np.ndarray, A: float, end_rest: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1-D path-speed profile of moves: duration, exit speed and peak speed (arrays of one shape).

    Path position is the max-norm joint distance in "seconds at full joint speed" (``L``); speeds are
    fractions of full speed (``u0 <= f``, the cruise speed ``f`` per move), ``A`` is the path acceleration
    (1/s). A move starts at ``u0``, accelerates at ``A`` toward ``f`` and, where ``end_rest``, brakes at ``A``
    to stop at its end (a move that cannot stop in time brakes uniformly; the spline fit retimes it and the
    verification has the last word).
    """
    u0sq = u0 * u0
    two_al = 2.0 * A * L
    u1 = np.minimum(np.sqrt(u0sq + two_al), f)
    dur = (u1 - u0) / A + np.maximum(L - (u1 * u1 - u0sq) / (2.0 * A), 0.0) / f
    if not end_rest.any():
        return dur, u1, u1
    up = np.minimum(f, np.sqrt((two_al + u0sq) / 2.0))
    can = u0sq <= two_al
    cruise = np.maximum(L - (up * up - u0sq) / (2.0 * A) - up * up / (2.0 * A), 0.0)
    t_rest = (up - u0) / A + cruise / np.maximum(up, 1e-12) + up / A
    dur_rest = np.where(can, t_rest, 2.0 * L / np.maximum(u0, 1e-12))
    return (
        np.where(end_rest, dur_rest, dur),
        np.where(end_rest, 0.0, u1),
        np.where(end_rest, np.where(can, up, u0), u1),
    )


def _profile_py(u0: float, L: float, f: float, A: float, end_rest: bool) -> tuple[float, float, float]:
    """:func:`_profile_arrays` for one move, in plain Python (the same formulas)."""
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
    # match[i, jj]: knot i is waypoint jj (within 1e-9 rad, as np.allclose with atol=1e-9)
    match = (np.abs(kq[:, None, :] - waypoints.q[None, :, :]) <= 1e-9 + 1e-5 * np.abs(waypoints.q[None])).all(
        2
    )
    j = 0
    for i, row in enumerate(match.tolist()):
        for jj in range(j, len(row)):
            if row[jj]:
                out[i] = waypoints.nodes[jj]
                j = jj
                break
    return out


__all__ = ["Plan", "PlanResult", "Planner", "PlannerConfig", "RobotModel"]


def _wall_times(t: np.ndarray) -> np.ndarray:
    return t


def _compiled_view(traj: Any) -> tuple[Trajectory, Callable[[np.ndarray], np.ndarray]] | None:
    """The :class:`Trajectory` whose knots the compiled check evaluates for ``traj``, and the map from wall
    times to its times: ``traj`` itself, or a view of one in another timing that names it
    (``base_trajectory``) and maps wall times to its times (``path_times``, e.g. the supervisor's
    speed-scaled view of the plan in execution); None for anything else (checked in NumPy)."""
    if isinstance(traj, Trajectory):
        return traj, _wall_times
    base = getattr(traj, "base_trajectory", None)
    path_times = getattr(traj, "path_times", None)
    if isinstance(base, Trajectory) and callable(path_times):
        return base, path_times
    return None
