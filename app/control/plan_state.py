"""The supervisor's bookkeeping of one robot: the plan in execution, the switch it waits for, a brake in
progress, and how a plan that sets a robot at rest moving is brought forward to the moment it is ready."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

from app.control.backup import BackupRequest, PlanOutcome
from app.control.trajectory_views import Goal, SpeedProfile, TrajectoryLike

SwitchReason = Literal["online_replan", "start", "resume", "improve"]


@dataclass
class ActivePlan:
    """The plan in execution (or the hold of a robot at rest), in path time ``tau``.

    Attributes:
        traj: The trajectory; a hold's runs with the clock.
        profile: Its parts' speeds along the path at scale 1.
        plan_id: Distinguishes it from the plans before and after it (a switch names the plan it branches
            from).
        kind: ``plan`` (toward a goal), ``emergency`` (the plan a stop switches to) or ``hold`` (at rest).
        complete: The plan ends at its goal (an emergency plan may end short of it).
        goal: The task pose it goes to, or None.
        checked_seq: The frame whose forecast it was last checked against.
        arrival_s: The planner's predicted arrival (runtime clock); None: ``traj.t_end``.
    """

    traj: TrajectoryLike
    profile: SpeedProfile
    plan_id: int
    kind: Literal["hold", "plan", "emergency"]
    complete: bool
    goal: Goal | None
    checked_seq: int
    arrival_s: float | None = None

    def under_way(self, tau: float) -> bool:
        """A plan (not a hold) with path left after path time ``tau``."""
        return self.kind != "hold" and tau < self.traj.t_end


@dataclass
class PendingSwitch:
    """A switch to a backup plan, scheduled by frame ``key``'s decision.

    Attributes:
        key: The frame whose backup it takes.
        t_switch: When it is due (runtime clock).
        tau_branch: Where it branches from the plan in execution (path time).
        plan_id: The plan in execution it branches from (a switch away from that plan voids it).
        reason: Why it was scheduled.
        violation_t: The predicted violation it avoids, if any.
        request: The backup request.
        outcome: The backup, once known.
        checked_seq: The frame whose forecast the backup passed last (-1: none; -2: failed it).
        early_seq: The frame at which bringing the switch forward was last tried (:func:`started_now`).
    """

    key: int
    t_switch: float
    tau_branch: float
    plan_id: int
    reason: SwitchReason
    violation_t: float | None
    request: BackupRequest | None = None
    outcome: PlanOutcome | None = None
    checked_seq: int = -1
    early_seq: int = -1

    @property
    def from_rest(self) -> bool:
        """The switch sets a robot at rest moving (a start, or a resume after a stop)."""
        return self.reason in ("start", "resume")

    def ready_at(self) -> float | None:
        """When its backup was ready (its request's time plus the compute time), None while unknown or
        where the backup is no plan."""
        out, req = self.outcome, self.request
        if out is None or req is None or out.status != "ok" or out.traj is None:
            return None
        return float(req.t_request + out.compute_s)


def started_now(pend: PendingSwitch, t: float) -> PendingSwitch | None:
    """A from-rest switch brought forward to ``t``, its plan shifted in time to start then; None where it
    cannot be (not ready by ``t``, due already, or its trajectory cannot be shifted).

    A robot at rest need not wait for the start deadline when its plan is ready earlier: the plan starts
    from rest where the robot stands, so starting it sooner is the same path at an earlier time. The
    shifted plan is a new plan in time, so the caller checks it against the latest forecast before it
    executes it (the switch's own check), and keeps the switch as scheduled where that check fails.
    """
    ready = pend.ready_at()
    if not pend.from_rest or ready is None or t < ready - 1e-9 or t >= pend.t_switch - 1e-9:
        return None
    assert pend.outcome is not None and pend.outcome.traj is not None
    moved = pend.outcome.shifted(float(t - pend.outcome.traj.t_start))
    if moved is None:
        return None
    return dataclasses.replace(pend, t_switch=float(t), tau_branch=float(t), outcome=moved, checked_seq=-1)


@dataclass
class Braking:
    """A brake in progress along the path, and the emergency plan that takes over at rest.

    Attributes:
        t0: When it began.
        tau0: Path time then.
        s0: Path scale then.
        rate: How fast the scale falls (1/s).
        t_stop: When the robot is at rest.
        tau_stop: Path time at rest.
        reason: Why the robot stops.
        emergency: The emergency plan, once planned.
        emergency_ready_t: When it may take over.
        emergency_tried: It was planned (whether or not one was found).
    """

    t0: float
    tau0: float
    s0: float
    rate: float
    t_stop: float
    tau_stop: float
    reason: str
    emergency: ActivePlan | None = None
    emergency_ready_t: float = math.inf
    emergency_tried: bool = False


def budget_part(
    active: ActivePlan,
    tau: float,
    s: float,
    *,
    held: bool,
    braking: bool,
    goal: Goal | None,
    gripper: bool,
    stopped: bool,
    person_in_way: bool,
    under_way_scale: float,
) -> str:
    """The time budget's part (:data:`app.control.supervisor_types.TIME_BUDGET`) of a servo tick: the plan
    in execution ``active`` at path time ``tau`` and scale ``s``; ``held``: an E-stop, a fault or a stale
    stream holds the robot; ``braking``: a stop's brake is on; ``gripper``: the gripper's dwell; ``stopped``:
    the supervisor's state after a stop; ``person_in_way``: the last plan from rest failed for the person;
    ``under_way_scale``: the path scale above which the robot counts as under way."""
    if held:
        return "stopped"
    if braking:
        return "braking" if s > under_way_scale else "stopped"
    if active.kind != "hold" and active.under_way(tau):
        if s <= under_way_scale:
            return "stopped"  # held at zero speed by the governor
        if float(active.profile.speed_at(tau).max()) <= 1e-6:
            return "planned_wait"
        return "moving_full" if s >= 1.0 - 1e-6 else "moving_scaled"
    if goal is None:
        return "idle"
    if gripper:
        return "gripper"
    if stopped:
        return "stopped"
    return "waiting_for_person" if person_in_way else "waiting_for_plan"
