"""The paper's replan state machine (section II-B): backup plans under a deadline, emergency plans, the
decision between *Nominal Execution* and *Collision Avoidance*, and speed scaling by separation. For every
new frame at ``T_i`` the :class:`Supervisor`

1. prepares the *backup plan* request from ``s = pi_curr(T_i + D)`` toward the current goal against the
   latest forecast, under the deadline ``D``; its result is usable from ``T_i + D``. Where the robot must
   start moving (at rest, or after an emergency plan) the plan starts from its current position (a plan from
   rest may take ``start_deadline_s``, 3 D by default; the robot stands still until it is ready and sets off
   then, the plan brought forward in time: ``start_when_ready``), and it is executed
   only if the latest forecast predicts no violation anywhere along it (``clear_start``): a robot at rest
   need not set off toward where the person is about to be, it waits and plans again;
2. checks the plan in execution against the *latest* forecast (:meth:`PlannerLike.first_violation`) and the
   robot's parts against the stop distance S_p(0) (ISO/TS 15066, the person's measured speed);
3. decides: *Nominal Execution* (continue; speed scaled by separation), or *Collision Avoidance*: a violation
   predicted after ``T_i + D`` schedules a switch to the backup plan at ``T_i + D`` (an *online replan*); a
   violation before ``T_i + D`` or a violated stop distance stops the robot and switches to the *emergency
   plan* (the person held at the current pose, horizon ``F + D``; a *stop & replan*). A planner that raises
   takes the emergency path too. A backup that misses its deadline produces no plan (the paper's rule), as one
   that finds no way produces none: the plan in execution, whose violation is still later than ``T_i + D``,
   is left to the next frames' backups, and the stop comes when that violation is due (a planner too slow for
   ``D`` thus costs the online replans it cannot deliver, not a stop of a robot that need not stop yet).

A backup plan of frame ``i`` is used by nothing but the switch that frame ``i``'s decision schedules (later
frames branch from the plan in execution at their own time; a switch invalidates the backups of the plan it
replaces), so it goes to the :class:`PlanJobs` only when that switch is scheduled: the decisions of computing
every frame's backup, without the plans nobody uses (live: a worker pool, at most ``ceil(D / F)`` in flight;
headless: when the switch is due, its measured compute time charged from ``T_i``). The emergency plan is
likewise computed when a stop is decided, from where the brake brings the robot to rest. The reactive
baseline is the same machine fed :meth:`HumanForecast.hold` of the current pose.

Execution uses a path-time parameter ``tau``, advancing by ``scale * dt``: speed scaling changes the timing
along the path, not the path; the scale rises no faster than a brake may lower it (the arm follows its
command). Where the robot will be at ``T_i + D`` is predicted with the fastest ramp, so that it reaches a
backup's branch point at or after ``T_i + D`` and the switch is continuous. Every plan is checked against the
latest forecast, in wall time with the current scale, before it is executed: a backup at the switch, an
emergency plan when the robot has come to rest.

Between frames a *speed governor* keeps ISO/TS 15066's protective separation at every servo tick, per robot
part (capsule): the part's separation to the last seen pose, less the person's worst-case approach since
that frame (:class:`SeparationModel`) and the part's own travel, must let the robot brake to rest without
the person coming closer than ``S_p`` at any instant of the braking (power and force limiting inside it).

Pure: no threads, no clock (time comes in as arguments); one lock lets :meth:`Supervisor.on_frame` and
:meth:`Supervisor.servo` be called from different threads.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np

from app.control.backup import BackupRequest, PlanJobs, PlanOutcome
from app.control.plan_state import ActivePlan, Braking, PendingSwitch, SwitchReason, budget_part, started_now
from app.control.scale_ramp import CreepWatch, StillWatch, jump_scale, ramp_distance, up_rate
from app.control.supervisor_types import (
    FrameDecision,
    SupervisorConfig,
    SupervisorCounters,
    SupervisorState,
    SupervisorStatus,
    TickCommand,
)
from app.control.trajectory_views import (
    Goal,
    HoldTrajectory,
    MakeTrajectory,
    PlannerLike,
    RobotGeometry,
    ScaledView,
    SpeedProfile,
    traj_state,
)
from app.planning.ssm_timing import predicted_arrival_from
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame
from app.safety.governor import (
    BRAKE_INSTANTS,
    NO_LAW,
    SCALE_GRID,
    PartSeparation,
    PathClosing,
    PFLLevels,
    RobotMotion,
    SeparationModel,
    ServoGovernor,
    SpeedScaleLaw,
    brake_rate,
    directed_pairs,
    governed_scale,
    nearest_approach,
    ssm_alone,
)
from app.safety.modes import PartMode, RegionMap, binding_part, part_modes
from app.safety.pfl import PFLModel, pfl_levels

log = logging.getLogger(__name__)

_EPS_SCALE = 1e-6

EventSink = Callable[[float, str, dict[str, Any]], None]

#: A path scale above this counts as under way (the time budget's moving parts, the stop & replans of a
#: moving robot); at or below it the robot is held still.
_UNDER_WAY_SCALE = 1e-3


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
        pfl: Power and force limiting inside ``S_p`` (:class:`app.safety.pfl.PFLModel`; the geometry then
            also gives ``human_static_gaps``); None: SSM alone.
        approach_floor_mps: (M,) each person capsule's least approach speed (ISO 13855's; the measured one
            where faster); None: the measured speed alone.
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
        pfl: PFLModel | None = None,
        approach_floor_mps: np.ndarray | None = None,
        timing: Any = None,
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
        self.pfl = pfl
        #: the governor's model that times the plans (:class:`app.safety.governor.GovernorModel`), or None: a
        #: plan setting the robot off is re-checked at the timing it predicts, as the planner verified it
        self.timing = timing
        self._floors = (
            None if approach_floor_mps is None else np.asarray(approach_floor_mps, dtype=np.float64)
        )
        self.config = config
        self.on_event = on_event
        self.timer = timer
        self.counters = SupervisorCounters()
        self.n_parts = int(np.asarray(geometry.part_speeds(q0[None], np.zeros((1, 6)))).shape[-1])
        self._lock = threading.RLock()
        self._plan_ids = 0
        self._generation = 0
        self._hold_halted = False  # the hold in force was left by a stop, not reached at a goal
        self._t = float(t0)
        self._tau = float(t0)
        self._s = 0.0
        self._creep = CreepWatch(self.config.creep_scale, self.config.creep_after_s)
        self._servo_dt = 0.0  # the last servo tick's length (s): how far the scale may jump from rest
        self._q_cmd = q0.copy()
        self._active = self._hold(q0, t0)
        self._pending: PendingSwitch | None = None
        self._brake: Braking | None = None
        self._goal: Goal | None = None
        self._not_before = -math.inf
        self._still = StillWatch(t0)  # since when the robot has (nearly) stood still with somewhere to go
        self._arrived: Goal | None = None
        self._reached: Goal | None = None  # the goal last reached (kept when the next is set)
        self._forecast: HumanForecast | None = None
        self._frame: HumanFrame | None = None
        self._seq = -1
        # separation bookkeeping for the governor
        L = self.n_parts
        # per robot part: the separation (none yet), the person's approach speed measured over a window and
        # their worst-case approach from its middle to the frame, the travel since (the compiled tick's input)
        self._parts = PartSeparation(np.full(L, math.inf), np.zeros(L), np.zeros(L), ssm_alone(L))
        self._travel = np.zeros(L)  # each part's travel since the robot's pose of the measurement (a bound)
        self._pairs: tuple[np.ndarray, np.ndarray] | None = None  # (L, M) distances and (M,) capsule speeds
        self._toward: tuple[ActivePlan, PathClosing] | None = None  # the parts' closing along the plan in
        # execution, measured at the last frame
        self._sep_person_t = -math.inf  # time of the frame the separation was measured on
        self._v_h_t = -math.inf  # the middle of the window the person's approach speed was measured over
        self._history: deque[HumanFrame] = deque(maxlen=16)
        self._v_cmd = np.zeros(L)  # speed bound of each part over the last tick (m/s)
        self._v_inst = np.zeros(L)  # speed of each part along the path at the last tick (m/s)
        self._stale = False
        self._estop = False
        self._fault = False
        self._stopped_latch = False
        self._moved_since_stop = 0.0
        self._retry_after = -math.inf
        # the last plan from rest failed because the person as forecast was in the way (PlanOutcome.blocked)
        self._person_in_way = False
        self._state: SupervisorState = "idle"

    # ------------------------------------------------------------------------------------------------
    # task interface
    # ------------------------------------------------------------------------------------------------

    def set_goal(self, goal: Goal | None, *, not_before: float = -math.inf) -> None:
        """Go to ``goal`` next, leaving no earlier than ``not_before`` (s); None: stay where you are."""
        with self._lock:
            self._goal = goal
            self._not_before = float(not_before)
            self._arrived = None
            self._person_in_way = False

    @property
    def goal(self) -> Goal | None:
        return self._goal

    def still_for(self, t: float) -> float:
        """How long (s) the robot has stood still at ``t`` with a goal it may leave for (:class:`StillWatch`:
        crept along its plans at a twentieth of their speed or less)."""
        return self._still.still_for(t)

    def reroute(self, goal: Goal, t: float) -> bool:
        """Go to ``goal`` instead of the goal in hand, from where the robot stands still (held there by the
        governor, or at rest; one that creeps stops first, a stop & replan): False, and nothing changed, where
        the robot is under way, brakes or is stopped."""
        with self._lock:
            if self._estop or self._fault or self._brake is not None or self._goal is None:
                return False
            if self._s > self._still.scale or self._still.still_for(t) <= 0.0:
                return False
            self._goal, self._arrived, self._person_in_way = goal, None, False
            self._pending, self._retry_after = None, -math.inf
            self._still.reset(t)
            self._emit(t, "rerouted", {"goal": goal})
            if self._s > _UNDER_WAY_SCALE or float(self._v_inst.max()) > 1e-6:
                self._emergency_path(t, reason="rerouted", violation_t=None)  # a creeping robot stops first
            else:  # (a new generation: the jobs in flight are void)
                self._activate_hold(self._q_cmd.copy(), float(t))
            return True

    def take_arrival(self) -> Goal | None:
        """The goal reached since the last call (once), else None."""
        with self._lock:
            g, self._arrived = self._arrived, None
            return g

    @property
    def state(self) -> SupervisorState:
        return self._state

    @property
    def speed_scale_law(self) -> SpeedScaleLaw | None:
        """The speed-scaling law the governor applies besides the braking envelope (None: the envelope
        alone)."""
        return self._speed_scale_law

    @speed_scale_law.setter
    def speed_scale_law(self, law: SpeedScaleLaw | None) -> None:
        self._speed_scale_law = law
        self._governor = ServoGovernor(
            self.ssm.kernel_params, NO_LAW if law is None else law.kernel_params, SCALE_GRID, BRAKE_INSTANTS
        )

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

    def intrusion(self, t: float) -> None:
        """The person appeared or jumped (a frame-to-frame motion no person makes): a protective stop. The
        robot brakes to rest along its path (when it is under way) and replans from there; the person's
        speed history is forgotten, so the next frames assume their fastest approach until it is measured
        again."""
        with self._lock:
            self._history.clear()
            self._v_h_t = -math.inf
            if self._estop or self._fault or self._brake is not None:
                return
            if not (self._s > 1e-6 and self._active.under_way(self._tau)):
                self._pending = None
                self._generation += 1
                return
            self._stop_and_replan(t, reason="intrusion", violation_t=None)
            brake, frame = self._brake, self._frame
        # the emergency plan from the stop point (checked against the latest forecast before it is taken):
        # without one tried, the brake would hold the robot for good
        if brake is not None and frame is not None:
            self._plan_emergency(brake, frame, gen_after=self._generation)
        elif brake is not None:
            with self._lock:
                brake.emergency_tried = True
                brake.emergency_ready_t = t

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

    def on_frame(
        self,
        frame: HumanFrame,
        forecast: HumanForecast,
        *,
        t_now: float,
        candidate: HumanForecast | None = None,
        ages_s: np.ndarray | None = None,
    ) -> FrameDecision:
        """Process a new frame ``frame`` (validated; every body in the cell) with the forecast of the
        method, at time ``t_now`` (``T_i``, the frame's arrival on the runtime clock); ``candidate``: the
        reactive method's forecast of the frame, whose plan each backup weighs against the method's own
        (:class:`BackupRequest`); ``ages_s`` (B,): how old each body's pose is (s; a lost body held where it
        was last seen, None: all seen now), each second of which counts as the fastest approach."""
        c0 = self.timer()
        cfg = self.config
        if frame.joints.shape != (frame.bodies * NUM_JOINTS, 3):
            raise ValueError(
                f"frame joints must be ({frame.bodies * NUM_JOINTS}, 3), got {frame.joints.shape}"
            )
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
            travel0 = self._travel.copy()
        # separation of each robot part now (robot at its last commanded pose vs the person as seen), and
        # the person's approach speed: how fast their motion closed the distance over the last window
        old = self._older_frame(frame.t - cfg.human_speed_window_s)
        pfl, pairs = None, None
        if frame.bodies == 0:  # nobody in the cell
            sep_parts = np.full(self.n_parts, np.inf)
            v_h0, t_mid = np.zeros(self.n_parts), frame.t
        elif self.pfl is not None or self._floors is not None:
            # ISO 13855's person: each capsule approaches at least at its region's speed; power and force
            # limiting inside S_p by region
            before = None if old is None else frame.matched(old)
            d_now, v_pairs = directed_pairs(
                self.geometry, q_now, frame.joints, before, None if old is None else frame.t - old.t,
                v_unknown_mps=self.ssm.human_speed_max_mps, floor_mps=self._floors,
            )  # fmt: skip
            t_mid = frame.t if old is None else 0.5 * (frame.t + old.t)
            if ages_s is not None and np.any(ages_s > 0.0):  # a lost body may have come closer since
                aged = np.repeat(np.asarray(ages_s, dtype=np.float64), d_now.shape[1] // frame.bodies)
                d_now = d_now - self.ssm.human_speed_max_mps * aged[None, :]
            sep_parts, v_h0 = nearest_approach(d_now, v_pairs, band_m=cfg.near_band_m)
            sep_parts = sep_parts - cfg.tracking_margin_m
            pfl, caps = self._pfl_levels(d_now, v_pairs, frame.joints)
            pairs = (d_now, caps)
        elif old is not None:
            # the person's directed speed toward each part: the fastest approach of the body parts that are
            # (nearly) the nearest to it (over all of them, so it does not jump when the nearest pair changes)
            sep_parts, v_h0 = self.geometry.near_person(
                q_now, frame.joints, frame.matched(old), frame.t - old.t, band_m=cfg.near_band_m
            )
            sep_parts = np.asarray(sep_parts, dtype=np.float64) - cfg.tracking_margin_m
            v_h0 = np.asarray(v_h0, dtype=np.float64)
            t_mid = 0.5 * (frame.t + old.t)
        else:  # no history yet: assume the fastest approach
            d = np.asarray(self.geometry.part_separations(q_now, frame.joints[None]), dtype=np.float64)
            sep_parts = d[0] - cfg.tracking_margin_m
            v_h0, t_mid = np.full(self.n_parts, self.ssm.human_speed_max_mps), frame.t
        if pfl is None:
            pfl = ssm_alone(self.n_parts)
        sep = float(sep_parts.min())
        toward = None
        if cfg.robot_toward and active.kind != "hold" and frame.bodies > 0:
            closing = PathClosing.measure(
                active.traj, active.profile, tau, frame.joints, self.geometry, horizon_s=cfg.toward_horizon_s
            )
            toward = None if closing is None else (active, closing)
        self._history.append(frame)
        with self._lock:
            self._toward, self._pairs = toward, pairs
            self._parts = PartSeparation(
                sep_parts,
                np.asarray(self.ssm.human_approach(v_h0, frame.t - t_mid)[0], dtype=np.float64),
                v_h0,
                pfl,
            )
            self._travel = np.maximum(self._travel - travel0, 0.0)  # travel since q_now was read
            self._sep_person_t = frame.t
            self._v_h_t = t_mid
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
            req = self._branch_request(seq, T, goal, forecast, active, tau, s, candidate)

        # 2. check the plan in execution against the latest forecast (outside the lock: it takes a while)
        moving_plan = active.under_way(tau)
        t_v: float | None = None
        if moving_plan:
            view = ScaledView(active.traj, t_ref=T, tau_ref=tau, scale=max(s, cfg.check_min_scale))
            t_v = self._first_violation(view, forecast, T, view.t_end)
        # the stop distance: a part that is to move is within S_p(0) of the person (at their measured speed;
        # the speed governor allows for what they may do before the next frame)
        # (every part of a robot that is to move: a part at rest on a moving robot must keep S_p(0) too)
        to_move = bool(np.any(active.profile.window_at(tau) > 1e-6))
        # (power and force limiting: a part may come within S_p(0) of a region it may touch, at that region's
        # speed, which the governor keeps; the capsules that admit no contact are at pfl.extra[:, 0])
        stop_distance = to_move and bool(
            np.any(sep_parts + pfl.extra[:, 0] <= self.ssm.s0_m + self.ssm.t_reaction_s * v_h0)
        )

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
            pend = self._pending
            overdue = pend is not None and pend.plan_id == active.plan_id and pend.t_switch + D < T
            if overdue and self._tau < pend.tau_branch - 1e-9 and self._s <= _UNDER_WAY_SCALE:
                # the governor holds the robot still short of the branch point (a creeping one gets there
                # late, as a switch may): it may never get there, and the backup would block every later
                # one, so plan again from here
                self._pending = None
            if moving_plan and (stop_distance or (t_v is not None and t_v <= T + D)):
                pend = self._pending
                if (
                    not stop_distance
                    and pend is not None
                    and pend.plan_id == active.plan_id
                    and pend.reason != "improve"
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
                if (
                    pend is not None
                    and pend.plan_id == active.plan_id
                    and pend.reason != "improve"
                    and pend.t_switch < t_v
                ):
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
                # a plan creeping at a low scale: weigh a backup that may arrive earlier (at the switch)
                if (
                    req is not None
                    and self.timing is not None
                    and self._pending is None
                    and (self._creep.due(T, s, active.plan_id))
                ):
                    self._schedule(req[0], req[1], active, "improve", None)
                    decision = "improve"
        brake = self._brake
        if decision == "stop_replan" and brake is not None:
            self._plan_emergency(brake, frame, gen_after=self._generation)
        return self._done(decision, t_v, sep, c0)

    def _done(self, action: str, t_v: float | None, sep: float, c0: float) -> FrameDecision:
        dt = self.timer() - c0
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
        active: ActivePlan,
        tau: float,
        s: float,
        candidate: HumanForecast | None,
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
            pr = active.profile
            rate = brake_rate(float(pr.window_at(tau).max()), pr.joint_window_at(tau), cfg.brake_decel_mps2,
                              cfg.brake_joint_decel)  # fmt: skip
            up = up_rate(cfg.scale_up_rate, rate, cfg.ramp_joint_accel, pr.top_joint_window_at(tau))
            # (the first tick may jump the scale: :func:`app.control.scale_ramp.jump_scale`)
            s_from = max(jump_scale(s, up, self._servo_dt, active.traj, active.profile, tau), s)
            tau_b = min(tau + ramp_distance(s_from, up, D), active.traj.t_end)
            t_start = T + D
            q_s, qd_s = traj_state(active.traj, tau_b)
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
            candidate=candidate,
            sets_off=not active.under_way(tau),
        )
        return req, float(tau_b)

    def _schedule(
        self, req: BackupRequest, tau_b: float, active: ActivePlan, reason: SwitchReason, t_v: float | None
    ) -> None:
        self.jobs.submit(req)
        self._pending = PendingSwitch(
            key=req.key,
            t_switch=req.t_start,
            tau_branch=tau_b,
            plan_id=active.plan_id,
            reason=reason,
            violation_t=t_v,
            request=req,
        )

    def _backup_passes(
        self,
        pend: PendingSwitch,
        out: PlanOutcome,
        t_now: float,
        tau: float,
        s: float,
        forecast: HumanForecast,
    ) -> float | None:
        """Re-check a backup against ``forecast`` as it would run from the switch; returns the violation time
        that forbids the switch, or None when it may be executed: a violation after ``t_now + D`` is left to
        the next frames' backups, except on a plan that starts the robot moving (``clear_start``)."""
        assert out.traj is not None
        cfg = self.config
        tau_new = out.traj.t_start + max(tau - pend.tau_branch, 0.0)
        t_ref = max(t_now, pend.t_switch) if tau < pend.tau_branch else t_now
        if pend.from_rest and self.timing is not None and t_ref - out.traj.t_start <= cfg.frame_period_s:
            # a plan that sets a robot at rest moving, checked as the planner verified it: at the timing the
            # governor is predicted to give it from its start, against the latest forecast
            try:
                t_v = self.planner.predicted_check(out.traj, forecast, timing=self.timing)[0]
            except Exception:
                log.exception("predicted_check raised; treating it as a violation now")
                t_v = t_ref
        else:
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
        rate = brake_rate(vmax, jmax, cfg.brake_decel_mps2, cfg.brake_joint_decel)
        if not math.isfinite(rate) or s0 <= 0:
            rate = max(s0, 1e-3) / 1e-3
        t_b = s0 / rate
        self._brake = Braking(
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
        if s0 > _UNDER_WAY_SCALE:
            self.counters.stop_replans_moving += 1
        self._stopped_latch = True
        self._moved_since_stop = 0.0
        # the path scale at the decision: 0 where the speed governor already held the robot still
        self._emit(t, "stop_replan", {"violation_t": violation_t, "reason": reason, "scale": round(s0, 4)})
        self._set_state("collision_avoidance", t)

    def _plan_emergency(self, brake: Braking, frame: HumanFrame, *, gen_after: int) -> None:
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
        em: ActivePlan | None = None
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
                em = ActivePlan(traj, prof, self._new_plan_id(), "emergency", False, self._goal, -1)
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

    def servo(self, t: float) -> TickCommand:
        """Advance execution to time ``t`` (s) and return the command for the robot."""
        with self._lock:
            dt = max(float(t) - self._t, 0.0)
            self._t = float(t)
            if self._estop or self._fault:
                self._s = 0.0
                self._v_cmd[:] = 0.0
                self._v_inst[:] = 0.0
                self._account(dt)
                return TickCommand(t, self._q_cmd.copy(), np.zeros(6), 0.0, True)
            if self._brake is not None:
                self._servo_brake(t)
            else:
                self._servo_governed(t, dt)
            active = self._active
            tau = min(self._tau, active.traj.t_end) if active.kind != "hold" else active.traj.t_end
            q, qd = traj_state(active.traj, tau)
            qd = qd * self._s
            if not active.under_way(self._tau):
                qd = np.zeros(6)
            self._travel += self._v_cmd * dt
            self._q_cmd = q
            self._still.tick(t, self._s, dt, waiting=self._goal is None or t < self._not_before)
            self._account(dt)
            # at rest anywhere but at a goal reached: the arm is to stay where it is
            halted = not np.any(qd) and (self._hold_halted or active.kind != "hold")
            return TickCommand(t, q.copy(), qd, self._s, bool(not np.any(qd)), halted=bool(halted))

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
            if pend is not None and pend.plan_id == active.plan_id and self.config.start_when_ready:
                self._start_when_ready(pend, t)
                active, pend = self._active, self._pending
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
        rate = brake_rate(vtop, jmax, cfg.brake_decel_mps2, cfg.brake_joint_decel)
        up = up_rate(
            cfg.scale_up_rate, rate, cfg.ramp_joint_accel, active.profile.top_joint_window_at(self._tau)
        )
        s = self._s
        self._servo_dt = dt if dt > 0.0 else self._servo_dt
        hi = jump_scale(s, up, dt, active.traj, active.profile, self._tau)
        if self._stale:
            s_target = 0.0
        elif vtop <= 1e-9:
            s_target = 1.0
        else:
            # the scales this tick can reach: up at the ramp rate, down at the brake rate (any at rest)
            at_rest = float(self._v_inst.max()) <= 1e-6
            lo = 0.0 if at_rest or not math.isfinite(rate) else s - rate * dt
            s_target = self._governed_scale(t, dt, s, vmax, rate, lo, hi)
        if s_target >= s:
            s_new = min(s_target, hi)
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

    def _start_when_ready(self, pend: PendingSwitch, t: float) -> None:
        """Set a robot at rest moving at ``t`` rather than at the start deadline, once its plan is ready and
        passes the latest forecast as it would run from ``t`` (:func:`started_now`). Caller holds the lock."""
        if (
            not pend.from_rest
            or pend.early_seq == self._seq
            or self._forecast is None
            or t < self._not_before
        ):
            return  # (never before the gripper's dwell has ended)
        if pend.outcome is None:
            pend.outcome = self.jobs.ready(pend.key, pend.request)
        early = started_now(pend, t)
        if early is None or early.outcome is None:
            return
        pend.early_seq = self._seq  # tried against this frame's forecast: again at the next frame
        if self._backup_passes(early, early.outcome, t, self._tau, self._s, self._forecast) is None:
            early.checked_seq = self._seq
            self._switch(early, t)

    def _switch(self, pend: PendingSwitch, t: float) -> None:
        """The pending switch is due: take the backup, re-check it against the latest forecast, execute it
        or take the emergency path. Caller holds the lock."""
        self._pending = None
        out = pend.outcome if pend.outcome is not None else self.jobs.take(pend.key, pend.request)
        self._record_plan(out, t)
        active = self._active
        moving = active.kind != "hold" and active.complete
        if out.status != "ok" and pend.from_rest:
            self._retry_after = t + self.config.retry_after_s
            self._person_in_way = out.blocked is not None  # only a failed search says where it was blocked
        if out.status != "ok":
            if out.status == "deadline_miss":
                self.counters.deadline_misses += 1
                limit = pend.request.deadline_s if pend.request is not None else None
                payload = {"elapsed_s": out.compute_s, "deadline_s": limit or self.config.deadline_s}
                self._emit(t, "deadline_miss", payload)
            else:
                self.counters.plan_failures += 1
                self._emit(t, "plan_failed", {"reason": f"backup {out.status}: {out.reason}"})
            # a planner fault takes the emergency path; a missed deadline produces no plan, as a search that
            # found no path produces none: both leave the plan in execution (its violation is still later than
            # the switch's T_i + D) to the next frames' backups, and its violation stops it when it is due
            if moving and pend.reason == "online_replan" and out.status == "error":
                self._emergency_path(t, reason=f"backup_{out.status}", violation_t=pend.violation_t)
            return
        if pend.checked_seq != self._seq and self._forecast is not None:
            t_v = self._backup_passes(pend, out, t, self._tau, self._s, self._forecast)
            if t_v is not None:
                self._emit(t, "plan_failed", {"reason": f"backup violates the latest forecast at {t_v:.3f}"})
                self.counters.plan_failures += 1
                if self.config.clear_start and pend.from_rest:
                    self._retry_after = t + self.config.retry_after_s
                    self._person_in_way = False
                if moving and pend.reason == "online_replan":
                    self._emergency_path(t, reason="backup_invalid", violation_t=t_v)
                return
        assert out.traj is not None and out.profile is not None
        if pend.reason == "improve":
            if out.arrival_s is None or self._forecast is None:
                return
            try:  # the rest of the plan in execution from the branch point, at the predicted timing
                mine = predicted_arrival_from(
                    active.traj, pend.tau_branch, pend.t_switch, self._forecast,
                    getattr(self.planner, "collision", None), self.timing,
                )  # fmt: skip
            except Exception:
                log.exception("predicting the plan in execution raised; keeping it")
                return
            if not out.arrival_s < mine - self.config.creep_gain_s:
                return  # the plan in execution arrives no later: keep it
            self.counters.improvements += 1
        tau_new = out.traj.t_start + max(self._tau - pend.tau_branch, 0.0)
        self.counters.count_choice(out.chosen, out.gain_s)
        pid = self._new_plan_id()
        self._active = ActivePlan(
            out.traj, out.profile, pid, "plan", True, self._goal, self._seq, out.arrival_s
        )
        self._person_in_way = False
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
        # the plan's predicted arrival against the executed one (its timing is on the runtime clock)
        predicted = active.traj.t_end if active.arrival_s is None else active.arrival_s
        self.counters.arrivals.append((float(predicted - active.traj.t_start), float(t - predicted)))
        q_goal = np.asarray(active.traj.q(active.traj.t_end)).reshape(6)
        self._arrived = active.goal
        self._reached = active.goal
        self._goal = None
        self._pending = None
        self._activate_hold(q_goal, t, arrived=True)
        self._set_state("nominal", t)

    # ------------------------------------------------------------------------------------------------
    # helpers
    # ------------------------------------------------------------------------------------------------

    def _new_plan_id(self) -> int:
        self._plan_ids += 1
        return self._plan_ids

    def _hold(self, q: np.ndarray, t: float) -> ActivePlan:
        traj = HoldTrajectory(q, t)
        prof = SpeedProfile.still(t, self.n_parts)
        return ActivePlan(traj, prof, self._new_plan_id(), "hold", False, None, -1)

    def _activate_hold(self, q: np.ndarray, t: float, *, arrived: bool = False) -> None:
        """Hold at ``q`` from ``t``: at a goal reached (``arrived``: the arm settles on it), or where a stop
        left the robot part of the way (the arm is told to stay where it is, :attr:`TickCommand.halted`)."""
        self._hold_halted = not arrived
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
        held = self._s <= _UNDER_WAY_SCALE
        if st == "nominal" and self._active.kind != "hold" and held and self._goal is not None:
            st = "stopped"  # held at zero speed by the governor
        c = self.counters
        c.state_time_s[st] += dt
        if not held and self._active.under_way(self._tau):
            c.moving_time_s += dt
            c.scale_time_s += self._s * dt
        part = self._budget_part()
        goal = self._reached if part == "gripper" else self._goal
        c.add_budget(part, "none" if goal is None else str(goal), dt, self._s)

    def _budget_part(self) -> str:
        """The :data:`TIME_BUDGET` part of the present tick (:func:`budget_part`). Caller holds the lock."""
        return budget_part(
            self._active, self._tau, self._s, held=self._estop or self._fault or self._stale,
            braking=self._brake is not None, goal=self._goal, gripper=self._t < self._not_before,
            stopped=self._state == "stopped", person_in_way=self._person_in_way,
            under_way_scale=_UNDER_WAY_SCALE,
        )  # fmt: skip

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

    def time_budget(self) -> tuple[dict[str, float], dict[str, dict[str, float]], float]:
        """:meth:`SupervisorCounters.budget_copy` under the lock, for readers on other threads (the per-goal
        budget gains a key at each new goal)."""
        with self._lock:
            return self.counters.budget_copy()

    def status(self) -> SupervisorStatus:
        """An immutable read-out (for snapshots; what limits each part is worked out after the lock)."""
        with self._lock:
            active, pend, modes_now = self._active, self._pending, self._part_modes()
            st = SupervisorStatus(
                t=self._t,
                state=self._effective_state(),
                scale=self._s,
                separation_m=math.inf,  # the limiting part's, below
                required_separation_m=math.nan,
                q=self._q_cmd.copy(),
                plan=None if active.kind == "hold" else active.traj,
                plan_tau=self._tau,
                backup=pend.outcome.traj if pend is not None and pend.outcome is not None else None,
                stale=self._stale,
                estopped=self._estop,
            )
        modes = modes_now()
        held = modes[binding_part(modes)]
        return replace(st, separation_m=held.separation_m, required_separation_m=held.required_m, modes=modes)

    def _pfl_levels(
        self, d_pairs: np.ndarray, v_pairs: np.ndarray, joints: np.ndarray
    ) -> tuple[PFLLevels, np.ndarray]:
        """Power and force limiting inside ``S_p`` (:meth:`app.safety.pfl.PFLModel.levels`; SSM alone
        without a model), each level at its own approach speed where the person is assumed at constant speed
        (ISO 13855's), else at the part's grown worst case; and the capsules' speeds (M,) behind them."""
        v = v_pairs if self.ssm.human_accel_mps2 <= 0.0 else None
        band = self.config.near_band_m
        if self.pfl is None:
            caps = np.full(d_pairs.shape[1], -1.0)
            return PFLLevels(*pfl_levels(d_pairs, caps, v, band_m=band)), caps
        gaps = self.geometry.human_static_gaps(joints, self.pfl.pinnable_index) if self.pfl.enabled else None
        return self.pfl.levels(d_pairs, v, gaps, band_m=band)

    def _part_modes(self) -> Callable[[], tuple[PartMode, ...]]:
        """What limits each part now (:func:`app.safety.modes.part_modes`, at the snapshot rate, from the
        governor's inputs, copied: call it after the lock; it changes none of them). Caller holds the lock."""
        cfg, prof, pairs, pfl = self.config, self._active.profile, self._pairs, self.pfl
        held = self._estop or self._fault or self._stale or self._brake is not None  # the robot is held
        held = held or (self._state == "stopped" and self._s <= _UNDER_WAY_SCALE)  # ... after a stop
        vmax = prof.window_at(self._tau)
        rate = brake_rate(float(vmax.max()), prof.joint_window_at(self._tau), cfg.brake_decel_mps2,
                          cfg.brake_joint_decel)  # fmt: skip
        robot = self._robot_motion(vmax, 0.0, rate, 1.0)
        regions = None  # each capsule's region, for every body
        if pairs is not None and pfl is not None:
            regions = RegionMap(*pairs, pfl.stacked(pairs[1].shape[0]).regions)
        return partial(
            part_modes, self._parts, robot._replace(closed_m=robot.closed_m.copy()), self._governor,
            scale=self._s, dt_h=self._t - self._v_h_t if math.isfinite(self._v_h_t) else math.nan, rate=rate,
            regions=regions, held=held,
        )  # fmt: skip

    def _older_frame(self, t: float) -> HumanFrame | None:
        """The newest remembered frame at or before ``t``."""
        for f in reversed(self._history):
            if f.t <= t + 1e-9:
                return f
        return None

    def _robot_motion(self, vmax: np.ndarray, dt: float, rate: float, hi: float) -> RobotMotion:
        """The robot's motion as the governor's tick reads it (:meth:`PathClosing.motion`: the closing
        measured at the last frame along the plan in execution where it covers this tick and a brake from
        ``hi``), else every part's whole speed and travel. Caller holds the lock."""
        tw = self._toward
        if tw is not None and tw[0] is self._active:
            motion = tw[1].motion(self._tau, vmax, self._travel, dt=dt, rate=rate, hi=hi)
            if motion is not None:
                return motion
        return RobotMotion(vmax, vmax, self._travel)

    def _governed_scale(
        self, t: float, dt: float, s: float, vmax: np.ndarray, rate: float, lo: float, hi: float
    ) -> float:
        """The governor's target scale for the tick from ``t`` to ``t + dt`` (compiled:
        :func:`app.safety.governor.governed_scale`; the tests compare it with a NumPy reference in
        ``tests/governor_reference.py``). Caller holds the lock."""
        dt_h = t + dt - self._v_h_t if math.isfinite(self._v_h_t) else math.nan
        robot = self._robot_motion(vmax, dt, rate, hi)
        return float(governed_scale(self._parts, robot, dt_h, s, dt, rate, lo, hi, self._governor))
