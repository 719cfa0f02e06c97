"""What the supervisor reports: its running totals of one trial (counts of replans and failures, planning
times, time per state, the trial's time budget, :data:`TIME_BUDGET`), the command of a servo tick, the
outcome of a frame's decision and its status read-out."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from app.control.trajectory_views import TrajectoryLike
from app.safety.modes import PartMode

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
