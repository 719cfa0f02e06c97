"""Per-trial metrics and timestamped events: the contract between the runtime and the study records.

The runtime fills a :class:`TrialMetrics` as a trial runs and emits :class:`TrialEvent` records; the study
database stores both (one metrics row per trial, one row per event) and the analysis reads them back.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

Method = Literal["proactive", "reactive"]
METHODS: tuple[Method, ...] = ("proactive", "reactive")

#: Kinds of events the runtime emits (payload keys in brackets).
EVENT_KINDS: tuple[str, ...] = (
    "trial_started",  # [method, seed]
    "trial_ended",  # [status, reason]
    "task_completed",  # [station, index]
    "state_changed",  # [from, to]
    "online_replan",  # [t_switch, violation_t]
    "stop_replan",  # [violation_t, reason, scale (the path scale at the decision; 0: held still)]
    "deadline_miss",  # [elapsed_s, deadline_s]
    "plan_failed",  # [reason]
    "rerouted",  # [goal]: the block in the gripper goes to another drop station (the person blocks its own)
    "stale_stream",  # [age_s]
    "stream_resumed",  # []
    "estop",  # [source]
    "robot_fault",  # [message]
    "violation",  # [part, separation_m, required_m, robot_speed_mps, human_speed_mps]
    "contact",  # [part, separation_m, robot_speed_mps]
    "intrusion",  # [speed_mps] of a body that jumped, or [separation_m] of a new body near the robot; [body]
    "body_appeared",  # [body]: a person came into the cell (their track id)
    "body_renamed",  # [body, tracker_id]: the tracker gave a person a new id; their track goes on
    "body_dropped",  # [body]: a person lost for longer than the hold time
)


@dataclass(frozen=True, slots=True)
class TrialEvent:
    """One timestamped event of a trial.

    Attributes:
        t: Seconds since the trial started (runtime clock: simulated in headless runs).
        kind: One of :data:`EVENT_KINDS`.
        payload: JSON-serialisable details.
    """

    t: float
    kind: str
    payload: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in EVENT_KINDS:
            raise ValueError(f"unknown event kind {self.kind!r}; expected one of {EVENT_KINDS}")
        if not math.isfinite(self.t):
            raise ValueError(f"event time must be finite, got {self.t}")


@dataclass(slots=True)
class TrialMetrics:
    """Everything measured in one trial. Counts are totals; ``*_per_task`` divide by completed tasks
    (by 1 when no task was completed, so that a trial without tasks still reports its counts).

    ``time_moving_s`` is the time the robot was under way on a plan (speed scale above zero, brakes
    included) and ``mean_speed_scale`` the average speed scale over that time (0 when it never moved): 1
    means that the plans ran at the speed they were planned for, and ``1 - mean_speed_scale`` is what speed
    and separation monitoring (and braking) took from them.

    The safety counts come from the ground-truth monitor (:mod:`app.safety.monitor`): ``violations``
    (SSM with PFL, ISO 13855's person), ``violations_person_faster`` (those a person faster than assumed
    opened), ``contacts`` and ``harmful_contacts`` are episodes, ``violation_time_s`` their total time,
    ``exceedance_s`` and ``max_approach_mps`` how long and how fast the true person approached faster than
    assumed; ``violations_iso`` (ISO 13855's constant speeds) and ``violations_measured_vh`` (the true
    measured speed), both SSM alone, are stress figures; ``min_separation_moving_m`` the smallest true
    separation while the robot moved; ``intrusions`` counts the frames in which the person appeared or jumped
    (a protective stop each).
    ``min_separation_m`` is the separation as the supervisor saw it (tracked frames).

    ``stop_replans_moving`` counts the stop & replans of a robot under way (its path scale above 0 at the
    decision); the others came to a robot the speed governor already held still (a hand within the stop
    distance of a part its plan was about to move): they stop nothing, their cost is the replan.

    ``budget_*_s`` are the trial's time budget (:data:`app.control.supervisor_types.TIME_BUDGET`: where its
    time went, the parts summing to ``duration_s``; ``budget_stopped_s`` counts the governor's holds at scale
    0 as well, unlike ``time_stopped_s``, the supervisor's stopped state). ``arrivals`` counts the plans that
    reached their goal; ``arrival_error_median_abs_s`` and ``arrival_error_bias_s`` compare their predicted
    arrival with the executed one (median absolute error; mean of executed minus predicted, positive: late),
    and ``median_plan_s`` is their median planned duration (all three NaN without arrivals).

    ``plans_forecast``, ``plans_reactive`` and ``plans_reactive_only`` count the plans executed after the
    reactive method's plan was weighed as a candidate against the method's own (the proactive method;
    :data:`app.control.backup.PlanChoice`): its own won, the reactive one arrived earlier (by
    ``reactive_gain_s`` in all, as predicted), or its own search found none. The reactive method weighs no
    candidate: all 0."""

    method: Method = "proactive"
    duration_s: float = 0.0
    completed_tasks: int = 0
    plans_computed: int = 0
    avg_planning_time_s: float = 0.0
    p95_planning_time_s: float = 0.0
    stop_replans: int = 0
    stop_replans_moving: int = 0
    online_replans: int = 0
    deadline_misses: int = 0
    emergency_plans: int = 0
    plan_failures: int = 0
    min_separation_m: float = math.inf
    violations: int = 0
    contacts: int = 0
    violation_time_s: float = 0.0
    violations_iso: int = 0
    violations_person_faster: int = 0
    harmful_contacts: int = 0
    violations_measured_vh: int = 0
    exceedance_s: float = 0.0
    max_approach_mps: float = 0.0
    intrusions: int = 0
    min_separation_moving_m: float = math.inf
    time_stopped_s: float = 0.0
    time_nominal_s: float = 0.0
    time_collision_avoidance_s: float = 0.0
    time_moving_s: float = 0.0
    mean_speed_scale: float = 0.0
    budget_moving_full_s: float = 0.0
    budget_moving_scaled_s: float = 0.0
    budget_braking_s: float = 0.0
    budget_stopped_s: float = 0.0
    budget_planned_wait_s: float = 0.0
    budget_gripper_s: float = 0.0
    budget_waiting_for_person_s: float = 0.0
    budget_waiting_for_plan_s: float = 0.0
    budget_idle_s: float = 0.0
    arrivals: int = 0
    arrival_error_median_abs_s: float = math.nan
    arrival_error_bias_s: float = math.nan
    median_plan_s: float = math.nan
    plans_forecast: int = 0
    plans_reactive: int = 0
    plans_reactive_only: int = 0
    reactive_gain_s: float = 0.0
    stale_stops: int = 0
    frames_received: int = 0
    frames_rejected: int = 0

    @property
    def stop_replans_per_task(self) -> float:
        return self.stop_replans / max(self.completed_tasks, 1)

    @property
    def online_replans_per_task(self) -> float:
        return self.online_replans / max(self.completed_tasks, 1)

    def to_dict(self) -> dict[str, Any]:
        """Flat, JSON-friendly dict including the derived per-task rates (inf becomes None)."""
        d = asdict(self)
        d["stop_replans_per_task"] = self.stop_replans_per_task
        d["online_replans_per_task"] = self.online_replans_per_task
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Stored fields (the derived per-task rates are not stored)."""
        return tuple(f.name for f in fields(cls))
