"""The planner's settings (:class:`PlannerConfig`), its result (:class:`PlanResult`) and what it needs from
the collision model (:class:`RobotModel`)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal, Protocol

import numpy as np

from app.planning.trajectory import Plan, Trajectory
from app.safety.ssm import SSMParams
from app.safety.stopping import UR5E_STOP, StoppingModel

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
        stopping: The robot's stopping model (:mod:`app.safety.stopping`, the governor's and the
            ground-truth monitor's): ``S_s`` of the clearance, from the fastest point's and fastest joint's
            speeds (:func:`app.safety.ssm.forecast_clearance`).
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
            completed fewer tasks (0.25 and 0 against 0.5 per method). Measured again with the stopping
            model's ``S_s`` in the clearance (tuning seeds 1000-1009, 300 s, tasks in all): proactive 5 and
            reactive 4 with it, 5 and 6 without; stop & replans 89 and 83 against 76 and 74; the robot
            moves faster where it moves (mean scale 0.17 and 0.15 against 0.10 and 0.09), 0 violations.
            With ``ssm_fallback_share`` 0.5, in the example cell with the stations moved out of that zone
            (``examples/workcell_stations_moved.toml``, tuning seeds 1000-1019, 300 s, tasks in all):
            proactive 88 and reactive 86 with it, 88 and 91 without; stop & replans 273 and 255 against
            244 and 261; mean scale 0.24 and 0.23 against 0.20 and 0.17; 0 violations, 0 contacts. The
            robot runs faster on longer ways round and arrives no sooner, so it stays off. With a perfect
            forecast (``--forecast oracle``) and ISO 13855's person for the governor (2.0 m/s, 8 m/s^2),
            the same cell, tuning seeds 1000-1009: 118 tasks with it, 114 without; the predictor 109 and
            111, reactive 116 either way. Only a perfect forecast gains by it, and too little to switch it
            on (under the default worst case the oracle completes 40 with it, 42 without).
        ssm_fallback_share: With ``ssm_aware_search``, the share of a query's compute budget that the search
            with the governor's clearance may take; where it finds no plan in it, the search runs again with
            the plain clearance in the rest of the budget (1: no second search). Without it (the example
            cell above, tuning seeds 1000-1009) the proactive robot waited 107 s per 300 s trial for a plan,
            with it 37 s (38 s with the option off).
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
        contact_only: Per person capsule (the order of :data:`app.planning.collision.HUMAN_CAPSULES`),
            whether the compiled trajectory checks (a plan's verification, the supervisor's check of the plan
            in execution against each new forecast, the check of the reactive candidate under the forecast)
            ask of it only ``Z_d``, no contact where the forecast expects the person, instead of the whole
            clearance: the body regions that power and force limiting lets the robot approach at their
            permissible contact speed, which the governor holds it to at run time (and the SSM-aware timing
            predicts). Empty: every capsule needs the whole clearance (SSM alone). The NumPy checks of a
            model without compiled ones ignore it.
        contact_only_search: The search's own checks (moves, samples, waits) take :attr:`contact_only` too;
            else they keep the whole clearance, and the plans they find pass the verification a fortiori.
        contact_speed_mps: Per person capsule (as :attr:`contact_only`), the robot speed (m/s, its fastest
            point) at or below which the compiled trajectory checks ask of a contact-only capsule no
            clearance at all: a contact at that speed stays within the region's permissible quasi-static
            speed (ISO/TS 15066 Annex A), so the robot may set off or go on beside a forecast hand that may
            touch it; faster, the contact clearance. Empty (or a capsule's value below 0): always the contact
            clearance.
    """

    ssm: SSMParams = field(default_factory=SSMParams)
    stopping: StoppingModel = UR5E_STOP
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
    ssm_fallback_share: float = 0.5
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
    contact_only: tuple[bool, ...] = ()
    contact_only_search: bool = False
    contact_speed_mps: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.speed_fraction must be in (0, 1], got {self.speed_fraction}")
        if not 0.0 < self.accel_fraction <= 1.0:
            raise ValueError(f"PlannerConfig.accel_fraction must be in (0, 1], got {self.accel_fraction}")
        for name in ("sample_dt_s", "verify_dt_s", "check_step_rad", "wait_step_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"PlannerConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 < self.ssm_fallback_share <= 1.0:
            raise ValueError(
                f"PlannerConfig.ssm_fallback_share must be in (0, 1], got {self.ssm_fallback_share}"
            )
        if self.shortcut_rounds < 1:
            raise ValueError(f"PlannerConfig.shortcut_rounds must be >= 1, got {self.shortcut_rounds}")
        if self.max_branch_tries < 1 or self.start_neighbors < 1:
            raise ValueError("PlannerConfig.max_branch_tries and start_neighbors must be >= 1")
        if self.heuristic_weight < 1.0:
            raise ValueError(f"PlannerConfig.heuristic_weight must be >= 1, got {self.heuristic_weight}")
        if self.speed_factor < 1.0:
            raise ValueError(f"PlannerConfig.speed_factor must be >= 1, got {self.speed_factor}")
        if self.contact_speed_mps and len(self.contact_speed_mps) != len(self.contact_only):
            raise ValueError(
                "PlannerConfig.contact_speed_mps needs one speed per capsule of contact_only "
                f"({len(self.contact_only)}), got {len(self.contact_speed_mps)}"
            )
        if any(not math.isfinite(v) for v in self.contact_speed_mps):
            raise ValueError(f"PlannerConfig.contact_speed_mps must be finite, got {self.contact_speed_mps}")

    def with_reaction_time(self, t_reaction_s: float) -> PlannerConfig:
        """These settings with the clearance's ``T_r`` set to the installation's (``S_r = v_r T_r``;
        :meth:`app.config.Settings.reaction_time_s`, the governor's and the monitor's)."""
        return replace(self, ssm=replace(self.ssm, t_reaction_s=float(t_reaction_s)))


#: The parts of a planning query's time (:attr:`PlanResult.phases_s`).
PHASES = ("search", "shortcut", "finish")

#: The reasons of a failed query where the forecast person is in the robot's way at either end (the planner
#: words its reasons with these; :func:`blocked_by_person` reads them back):
#: the robot cannot leave where it stands, the person is (or is forecast) within its clearance now;
START_BLOCKED = "start configuration violates the separation at t_start"
#: the goal is occupied: the person is forecast there for good, or from some time on;
GOAL_BLOCKED = "goal blocked by the person"
#: every way into the goal is blocked once the person's forecast holds still.
GOAL_WAYS_BLOCKED = "goal unreachable: every way into it is blocked once the person holds still"

#: Where the person blocks a query: ``start`` (the robot cannot leave yet) or ``goal`` (it is occupied).
Blocked = Literal["start", "goal"]


def blocked_by_person(reason: str) -> Blocked | None:
    """Where the person as forecast blocks a query that failed with ``reason`` (a :attr:`PlanResult.reason`):
    ``start``, ``goal``, or None where the query failed for another reason (no way found in time, a
    trajectory that failed its verification, a missed deadline, bad input) or did not fail."""
    if reason.startswith(START_BLOCKED):
        return "start"
    if reason.startswith((GOAL_BLOCKED, GOAL_WAYS_BLOCKED)):
        return "goal"
    return None


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
        phases_s: Of :meth:`Planner.plan`'s query, the time (s) in each of :data:`PHASES`: ``search``
            (setting up the separation check and the time-variant A*), ``shortcut`` (shortening the found
            path) and ``finish`` (fitting the trajectory, its SSM-aware timing and its verification); None
            where the query ended before any search (and for emergency plans).
    """

    ok: bool
    plan: Plan | None
    reason: str
    expanded: int
    compute_s: float
    trajectory: Trajectory | None = None
    arrival_s: float | None = None
    phases_s: Mapping[str, float] | None = None

    @property
    def blocked(self) -> Blocked | None:
        """Where the person as forecast blocked a failed query (:func:`blocked_by_person`); None for a
        plan."""
        return None if self.ok else blocked_by_person(self.reason)


def _paired_options(model: RobotModel) -> set[str]:
    """The keyword options of ``model.distance_to_human_paired`` (``segments``, ``links``, ``capsules``)."""
    try:
        params = inspect.signature(model.distance_to_human_paired).parameters
    except (TypeError, ValueError):
        return set()
    return {name for name in ("segments", "links", "capsules") if name in params}
