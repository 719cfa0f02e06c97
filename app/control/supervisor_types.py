"""The supervisor's configuration (:class:`SupervisorConfig`) and what it reports: its running totals of one
trial (counts of replans and failures, planning times, time per state, the trial's time budget,
:data:`TIME_BUDGET`), the command of a servo tick, the outcome of a frame's decision and its status
read-out."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from app.control.metrics import Method
from app.control.trajectory_views import TrajectoryLike
from app.planning.kinematics import QDD_MAX
from app.safety.modes import PartMode
from app.safety.stopping import UR5E_STOP

SupervisorState = Literal["idle", "nominal", "collision_avoidance", "stopped", "estop", "fault"]
#: Every state a :class:`~app.control.supervisor.Supervisor` can be in.
SUPERVISOR_STATES: tuple[SupervisorState, ...] = (
    "idle",
    "nominal",
    "collision_avoidance",
    "stopped",
    "estop",
    "fault",
)

#: The parts of a trial's time budget (:attr:`SupervisorCounters.budget_s`), every servo tick in one of them:
#:
#: - ``moving_full``: under way on a plan at full speed (scale 1);
#: - ``moving_scaled``: under way, slowed by the speed governor (scale between 0 and 1);
#: - ``braking``: braking to rest after a stop decision;
#: - ``stopped``: held still by the supervisor (after a stop, by the governor at scale 0, while the stream is
#:   stale, E-stop, fault);
#: - ``planned_wait``: a wait that the plan itself holds (the time-variant search waits for the person);
#: - ``gripper``: at a station, gripping or releasing (the task's dwell before it may leave);
#: - ``waiting_for_person``: at rest with somewhere to go, the person in the way as forecast: the last plan
#:   from rest failed because its goal is occupied (a hand at the station) or because the robot cannot leave
#:   where it stands (the person is fetching the block it has just placed)
#:   (:attr:`app.control.backup.PlanOutcome.blocked`);
#: - ``waiting_for_plan``: at rest with somewhere to go, and no safe plan yet for another reason (a plan being
#:   computed, no way found in time, a missed deadline, a plan that a newer forecast broke);
#: - ``idle``: nothing to do.
TIME_BUDGET: tuple[str, ...] = (
    "moving_full",
    "moving_scaled",
    "braking",
    "stopped",
    "planned_wait",
    "gripper",
    "waiting_for_person",
    "waiting_for_plan",
    "idle",
)


@dataclass
class SupervisorCounters:
    """Running totals of one trial."""

    stop_replans: int = 0
    #: the stop & replans of a robot under way (path scale above 0 at the decision); the others came to a
    #: robot the speed governor already held still
    stop_replans_moving: int = 0
    online_replans: int = 0
    #: switches to a backup predicted to arrive earlier than the creeping plan in execution
    improvements: int = 0
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
    #: where the time went (:data:`TIME_BUDGET` parts; they sum to the supervised time)
    budget_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(TIME_BUDGET, 0.0))
    #: the same parts per goal: the task pose the robot is heading for (or waiting to leave for), the gripper
    #: dwell under the pose where it grips or releases, ``"none"`` with no goal
    budget_by_goal_s: dict[str, dict[str, float]] = field(default_factory=dict)
    #: the integral of the scale over ``moving_scaled`` time
    scaled_scale_s: float = 0.0
    #: per plan that reached its goal: (planned duration (s), executed minus predicted arrival (s))
    arrivals: list[tuple[float, float]] = field(default_factory=list)
    #: of the plans executed after weighing the reactive method's candidate: how many were the forecast's
    #: own, the reactive one that arrives earlier, or the reactive one where the forecast's found none
    #: (:data:`app.control.backup.PlanChoice`), and the predicted time the reactive ones gained (s)
    plan_choices: dict[str, int] = field(
        default_factory=lambda: {"forecast": 0, "reactive": 0, "reactive_only": 0}
    )
    reactive_gain_s: float = 0.0

    def count_choice(self, chosen: str | None, gain_s: float) -> None:
        """Count an executed plan's :attr:`PlanOutcome.chosen` (None: no candidate was weighed)."""
        if chosen is not None:
            self.plan_choices[chosen] += 1
            self.reactive_gain_s += gain_s

    def add_budget(self, part: str, goal: str, dt: float, scale: float) -> None:
        """Count ``dt`` seconds of the time budget's ``part`` (:data:`TIME_BUDGET`) toward ``goal`` (the
        task pose, ``"none"`` without one); ``scale``: the speed scale meanwhile."""
        self.budget_s[part] += dt
        per_goal = self.budget_by_goal_s.get(goal)
        if per_goal is None:
            per_goal = self.budget_by_goal_s[goal] = dict.fromkeys(TIME_BUDGET, 0.0)
        per_goal[part] += dt
        if part == "moving_scaled":
            self.scaled_scale_s += scale * dt

    def budget_copy(self) -> tuple[dict[str, float], dict[str, dict[str, float]], float]:
        """A copy of the time budget: seconds per part, the same per goal, and the integral of the scale
        over ``moving_scaled``."""
        by_goal = {goal: dict(parts) for goal, parts in self.budget_by_goal_s.items()}
        return dict(self.budget_s), by_goal, self.scaled_scale_s


@dataclass(frozen=True, slots=True)
class TickCommand:
    """What the supervisor tells the robot at one servo tick (the set-point that the robot's servo follows
    is :class:`app.cell.joint_tracking.ServoCommand`).

    Attributes:
        t: Time of the tick (s).
        q: (6,) joint positions (rad).
        qd: (6,) joint velocities (rad/s).
        scale: Speed scale in [0, 1] applied along the path.
        hold: True when the robot is meant to stand still.
        halted: True when it stands still part of the way along a plan (the speed governor or a brake has
            brought the scale to 0): the robot may be told to stay where it is rather than to close the few
            milliradians its servo lags the command by (:meth:`app.control.engine.TrialEngine.servo_tick`).
    """

    t: float
    q: np.ndarray
    qd: np.ndarray
    scale: float
    hold: bool
    halted: bool = False


@dataclass(frozen=True, slots=True)
class FrameDecision:
    """The outcome of one frame's decision (for logs, tests and the loop benchmark).

    Attributes:
        action: ``nominal``, ``online_replan`` (switch scheduled), ``stop_replan``, ``start`` (switch
            scheduled from rest), ``resume`` (switch scheduled after an emergency plan), ``improve`` (a
            backup scheduled for a creeping plan, taken where it arrives earlier), ``hold`` (nothing to do),
            ``skipped`` (the state changed while deciding).
        violation_t: Predicted violation time of the plan in execution, if any (s).
        separation_m: Measured separation minus the tracking margin (m).
        decide_s: Compute time of the decision itself (s), without the backup plan's search.
    """

    action: str
    violation_t: float | None
    separation_m: float
    decide_s: float


@dataclass(frozen=True, slots=True)
class SupervisorStatus:
    """An immutable read-out of the supervisor, for snapshots.

    Attributes:
        t: Time of the last servo tick (s).
        state: One of :data:`SUPERVISOR_STATES`.
        scale: Current speed scale.
        separation_m: The separation (m) of the part that limits the robot (the smallest allowed scale)
            from the body regions it keeps ``S_p`` from at its speed, as last measured; inf when nobody was
            seen.
        required_separation_m: The separation (m) the speed governor holds that part to at its current
            speed (:attr:`app.safety.modes.PartMode.required_m`; for a stopped part, what it needs to move).
        q: (6,) last commanded configuration.
        plan: The trajectory in execution (None when holding).
        plan_tau: Path time in it.
        backup: The trajectory of a pending switch, when known.
        stale: The stream is stale (the robot is held).
        estopped: E-stop latched.
        modes: What limits each robot part now (:func:`app.safety.modes.part_modes`), in the parts' order.
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
    modes: tuple[PartMode, ...] = ()


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
        scale_up_rate: Largest increase of the speed scale per second (1/s), at most the brake's rate and
            what ``ramp_joint_accel`` allows the fastest joint.
        ramp_joint_accel: The joints' acceleration limit (rad/s^2) the scale's ramp keeps to, so that the arm
            follows its command (it brakes faster than it may speed up: the stopping model's decelerations).
        tracking_margin_m: Tracking error of a frame: subtracted from measured separations and used as the
            margin of the held pose (reactive forecast, emergency plan).
        human_speed_window_s: Window (s) over which the person's speed is measured.
        near_band_m: The person's parts within this much of being the nearest to a robot part count for
            the speed of the person near that part (m).
        retry_after_s: After a failed plan to start (or resume) moving, the next attempt waits this long (s).
        clear_start: A plan that starts the robot from rest (or resumes it) is executed only if the latest
            forecast predicts no violation anywhere along it (timed as the governor is predicted to run it
            where the supervisor has the governor's model, else at ``check_min_scale``); else the robot
            stays at rest and plans again after ``retry_after_s``. False: only a violation before
            ``T_i + D`` forbids it, as for a backup that replaces a plan in execution.
        resume_travel_m: After a stop & replan, the robot is under way again (a new encounter can stop it
            again) once it has moved this far (m).
        check_dt_s: Time step of the checks of a plan against a forecast (s).
        check_min_scale: Least scale at which a slowed or stopped robot's plan is timed for the checks.
        profile_window_s: Look-ahead of the speed governor along the path (s).
        robot_toward: The governor takes each part's speed *toward* the person (ISO/TS 15066's directed
            ``v_r``, measured at every frame along the path ahead: :func:`app.safety.governor.closing_bound`),
            not its whole speed (False: as if it moved straight at the person).
        toward_horizon_s: How far along the path (path time, s) the directed speed is measured at each
            frame; the governor falls back to the whole speed where a brake could end beyond it (or on a
            plan switched to since the frame).
        emergency_horizon_s: Horizon of the emergency plan; default F + D.
        creep_scale: A plan in execution held below this path scale for ``creep_after_s`` is weighed against
            a backup from its branch point (both at the governor's predicted timing against the latest
            forecast; it needs ``timing``), taken where it arrives ``creep_gain_s`` earlier; None: never.
        creep_after_s: How long the plan must creep before that, and how often it is weighed (s).
        creep_gain_s: How much earlier the backup must arrive (s).
        start_when_ready: A robot at rest sets off as soon as its plan is ready and passes the latest
            forecast as it would run from then (its path the same, its timing earlier), not at the start
            deadline; False: at the start deadline.
    """

    method: Method = "proactive"
    deadline_s: float = 0.1
    start_deadline_s: float | None = None
    frame_period_s: float = 1.0 / 30.0
    planner_workers: int = 1
    brake_decel_mps2: float = UR5E_STOP.decel_mps2
    brake_joint_decel: float = UR5E_STOP.slowest_joint_decel_radps2
    scale_up_rate: float = 4.0
    ramp_joint_accel: float = float(np.min(QDD_MAX))
    tracking_margin_m: float = 0.02
    human_speed_window_s: float = 0.1
    near_band_m: float = 0.25
    retry_after_s: float = 0.2
    clear_start: bool = True
    resume_travel_m: float = 0.03
    check_dt_s: float = 0.04
    check_min_scale: float = 0.5
    profile_window_s: float = 0.6
    robot_toward: bool = True
    toward_horizon_s: float = 0.9
    emergency_horizon_s: float | None = None
    creep_scale: float | None = None
    creep_after_s: float = 0.5
    creep_gain_s: float = 0.2
    start_when_ready: bool = True

    def __post_init__(self) -> None:
        if self.method not in ("proactive", "reactive"):
            raise ValueError(f"method must be 'proactive' or 'reactive', got {self.method!r}")
        if self.deadline_s <= 0 or self.frame_period_s <= 0:
            raise ValueError("deadline_s and frame_period_s must be positive")
        if not (math.isfinite(self.toward_horizon_s) and self.toward_horizon_s > 0):
            raise ValueError(f"toward_horizon_s must be a finite number > 0, got {self.toward_horizon_s!r}")

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
