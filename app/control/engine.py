"""One trial's wiring, shared by the live runtime and the headless runner:
source -> validation -> predictor -> supervisor -> trajectory -> robot, plus the task, metrics and events.
The proactive method's forecast also expects the person to fetch each block the robot places
(:mod:`app.control.anticipation`, ``Settings.anticipate_fetch``).

:class:`TrialEngine` has no threads and no clock of its own: the caller invokes
:meth:`TrialEngine.frame_tick` at the camera rate and :meth:`TrialEngine.servo_tick` at the robot
rate with the current time (the live runtime from its threads on the wall clock, the headless runner
from one loop on the simulated clock).

The planning stack and the robot's body are in :mod:`app.control.stack`, what a trial produces and shows
in :mod:`app.control.results`.

Safety is judged by the ground-truth monitor (:class:`app.safety.monitor.GroundTruthMonitor`) at every
servo tick: against the *true* person where the caller has one (``truth``: the simulated operator or a
replayed clip behind a tracker model), else against the tracker's frames (a real cell, where nothing
better exists). A frame in which the person moved faster than a person can is an *intrusion* (someone
appeared, a joint jumped, or the tracker jumped to another person): a protective stop, counted apart.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.cell.bodies import pad_bodies
from app.cell.robot import RobotBackend, RobotConnectionError, RobotState
from app.cell.validation import FrameValidator, StaleWatchdog, ValidatedSource
from app.config import Settings, WorkCell
from app.control.anticipation import FetchAnticipation, FetchAnticipationParams
from app.control.backup import BackupComputer, PlanJobs
from app.control.metrics import Method, TrialEvent, TrialMetrics
from app.control.people import People, PeopleOptions, PeopleUpdate
from app.control.results import Snapshot, TrialFrames, TrialResult, TrialStatus
from app.control.stack import CellGeometry, PlanningStack, pfl_model
from app.control.supervisor import FrameDecision, Supervisor, SupervisorConfig
from app.control.supervisor_types import TickCommand
from app.control.task import TaskExecutive
from app.planning.collision import reach_fingertips, segment_distance
from app.prediction.forecast import HumanForecast, Predictor
from app.prediction.skeleton import JOINT_INDEX, HumanFrame
from app.safety.governor import GovernorModel, SeparationModel, SpeedScaleLaw
from app.safety.monitor import GroundTruthMonitor
from app.safety.pfl import PFLModel
from app.safety.stopping import UR5E_STOP

log = logging.getLogger(__name__)

#: A robot halted part of the way along its plan is told to stay where it is when it is within this much of
#: the command (rad): the few milliradians its servo lags by (6.5 mrad at 0.74 rad/s in the simulated arm,
#: one servo tick; a safety bound, not tuned), not a position it was never commanded near.
_HALT_TOLERANCE_RAD = 0.02

#: The directed speed (m/s) that the supervisor measures on a still person, per metre of tracker noise per
#: joint and axis over its speed window: for the SSM-aware timing's prediction of the governor
#: (:class:`app.safety.governor.GovernorModel.speed_noise_mps`). Tuned on seeds 1000-1003: the median of the
#: measured directed speed of the simulated operator at work, 0.33 m/s with 1 cm of noise over 0.1 s.
SPEED_NOISE_GAIN = 3.3


# --------------------------------------------------------------------------------------------------------
# The engine
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class EngineOptions:
    """How a :class:`TrialEngine` runs.

    Attributes:
        monitor: Judge the trial with the ground-truth monitor at every servo tick.
        servo_period_s: The robot's command period (s): one controller cycle of the reaction time ``T_r``.
        intrusion_speed_mps: A frame in which the body (its median joint) moved faster than this since the
            previous frame, or any joint faster than twice this, is an intrusion
            (:func:`app.safety.monitor.is_intrusion`).
        record_frames: Keep the frames for the study database.
        tracking_margin_m: Tracking error of a frame (m) (see :class:`SupervisorConfig`).
        plan_margin_m: Extra clearance (m) the plans keep from the forecast person (both methods alike): room
            for the speed governor, which slows a robot that passes close to a person.
        human_accel_mps2, human_speed_max_mps: The person's worst case for the speed governor (see
            :class:`~app.safety.governor.SeparationModel`): how fast their speed may change between
            frames and during a brake, and their fastest approach (None: ``Settings.human_accel_max_mps2``,
            ``Settings.human_speed_max_mps``).
        pick_dwell_s, place_dwell_s: Gripper times (s).
    """

    monitor: bool = True
    servo_period_s: float = 1 / 125
    intrusion_speed_mps: float = 5.0
    record_frames: bool = True
    tracking_margin_m: float = 0.02
    human_accel_mps2: float | None = None
    human_speed_max_mps: float | None = None
    plan_margin_m: float = 0.0
    pick_dwell_s: float = 0.4
    place_dwell_s: float = 0.4


EventListener = Callable[[TrialEvent], None]


def supervisor_config(settings: Settings, method: Method, options: EngineOptions) -> SupervisorConfig:
    """The supervisor's configuration for a trial of ``method`` under ``settings``."""
    return SupervisorConfig(
        method=method,
        deadline_s=settings.deadline_s,
        start_deadline_s=settings.start_deadline_s,
        start_when_ready=settings.start_when_ready,
        frame_period_s=settings.frame_period_s,
        planner_workers=settings.planner_workers,
        tracking_margin_m=options.tracking_margin_m,
        robot_toward=settings.robot_toward,
        creep_scale=settings.creep_switch_scale,
    )


def governor_model(
    settings: Settings,
    ssm: Any,
    config: SupervisorConfig,
    options: EngineOptions,
    *,
    separation: SeparationModel | None = None,
) -> GovernorModel:
    """The speed governor of a trial, as the planner predicts it (:class:`GovernorModel`): its separation
    model (``T_r`` of these settings, the one stopping model, the person's worst case), brake and
    speed-scaling law, and what it measures (the frame as old as it gets before the next one arrives, the
    directed speed that the tracker's noise gives a still person). ``ssm``: the planner's
    :class:`app.safety.ssm.SSMParams`; ``separation`` replaces the separation model (tests)."""
    ssm = dataclasses.replace(ssm, t_reaction_s=settings.reaction_time_s(options.servo_period_s))
    if separation is None:
        v_max = (
            settings.assumed_human_speed_mps
            if options.human_speed_max_mps is None
            else options.human_speed_max_mps
        )
        accel = options.human_accel_mps2
        if accel is None:
            accel = settings.assumed_human_accel_mps2
        separation = SeparationModel.from_ssm(
            ssm,
            human_speed_max_mps=v_max,
            human_accel_mps2=accel,
            stop_decel_mps2=UR5E_STOP.decel_mps2,
        )
    pfl = pfl_model(settings)
    floors = approach_floors(settings, pfl)
    return GovernorModel(
        separation=separation,
        brake_decel_mps2=config.brake_decel_mps2,
        brake_joint_decel=config.brake_joint_decel,
        tracking_margin_m=config.tracking_margin_m,
        speed_window_s=config.human_speed_window_s,
        sensing_age_s=settings.tracker_latency_s + settings.frame_period_s + settings.processing_time_s,
        near_band_m=config.near_band_m,
        speed_noise_mps=SPEED_NOISE_GAIN * settings.tracker_noise_m / config.human_speed_window_s,
        lookahead_s=config.profile_window_s,
        # the standard's constant-speed law (T_s fixed at SSMParams.t_stop_s) beside the braking envelope, for
        # the what-if person measured from their speed; ISO 13855's person is the envelope's, at constant
        # speed with the stopping model's T_s (the same S_p = v_h (T_r + T_s) + ..., T_s the robot's own)
        law=SpeedScaleLaw(ssm) if settings.human_model == "cmu_p99" else None,
        robot_toward=config.robot_toward,
        pfl_caps_mps=tuple(float(v) for v in pfl.transient_mps) if pfl.enabled else (),
        approach_floor_mps=() if floors is None else tuple(float(v) for v in floors),
    )


def approach_floors(settings: Settings, pfl: PFLModel | None = None) -> np.ndarray | None:
    """(M,) each person capsule's least approach speed (m/s) that the governor assumes: ISO 13855's by region
    (``Settings.human_model = "iso13855"``: never lower; the measured one where faster); None for the
    what-if person (the measured speed alone). ``pfl``: the trial's model (default: built here)."""
    if settings.human_model != "iso13855":
        return None
    return (pfl if pfl is not None else pfl_model(settings)).iso_speeds_mps


class TrialEngine:
    """One trial of the cell: see the module docstring.

    Args:
        stack: The planning stack of the cell.
        settings: D, F, workers, method defaults.
        robot: The robot backend (its clock is the caller's).
        source: The human source behind validation (:class:`ValidatedSource`).
        predictor: The motion predictor (proactive method); None for the reactive method.
        jobs_factory: ``(BackupComputer, SupervisorConfig) -> PlanJobs``.
        method: ``proactive`` or ``reactive``.
        duration_s: Trial length (s).
        seed: Seed of the assembly sequence.
        t0: Start time on the caller's clock (s).
        options: Engine options.
        on_event: Called with every event (already in the trial's list).
        separation: The speed governor's model (default: from the planner's SSM parameters).
        timer: Monotonic timer for compute times.
        truth: The true person, ``truth(t) -> (J, 3)`` at any time (simulation); None: the monitor judges
            against the tracker's frames.
    """

    def __init__(
        self,
        *,
        stack: PlanningStack,
        settings: Settings,
        robot: RobotBackend,
        source: ValidatedSource,
        predictor: Predictor | None,
        jobs_factory: Callable[[BackupComputer, SupervisorConfig], PlanJobs],
        method: Method,
        duration_s: float,
        seed: int,
        t0: float,
        options: EngineOptions | None = None,
        on_event: EventListener | None = None,
        separation: SeparationModel | None = None,
        timer: Callable[[], float] = time.perf_counter,
        truth: Callable[[float], np.ndarray] | None = None,
    ) -> None:
        if method not in ("proactive", "reactive"):
            raise ValueError(f"method must be 'proactive' or 'reactive', got {method!r}")
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        if method == "proactive" and predictor is None:
            raise ValueError("the proactive method needs a predictor")
        self.stack = stack
        self.settings = settings
        self.robot = robot
        self.source = source
        self.predictor = predictor
        self.method: Method = method
        self.duration_s = float(duration_s)
        self.seed = int(seed)
        self.t0 = float(t0)
        # not stale before the first frame can have arrived (the tracker's latency)
        source.expect_frames_from(self.t0)
        self.options = options or EngineOptions()
        self.on_event = on_event
        self.events: list[TrialEvent] = []
        self.config = supervisor_config(settings, method, self.options)
        # T_r of this system (tracker latency, frame, processing, controller cycle) and the one stopping
        # model: the governor and the monitor use the same figures; and what the governor will do, for the
        # SSM-aware timing of plans (the same separation model and law as the supervisor's)
        self.reaction_time_s = settings.reaction_time_s(self.options.servo_period_s)
        if not math.isclose(stack.ssm.t_reaction_s, self.reaction_time_s, rel_tol=0.0, abs_tol=1e-9):
            raise ValueError(
                f"the planning stack's clearance assumes T_r = {stack.ssm.t_reaction_s:.4f} s, this "
                f"system's is {self.reaction_time_s:.4f} s (tracker latency, frame, processing, controller "
                "cycle): build it with PlanningStack.for_cell(cell, t_reaction_s=...) or "
                "stack.with_reaction_time(...)"
            )
        self.pfl = pfl_model(settings)  # the trial's power and force limiting (supervisor and judge)
        self.governor_model = governor_model(
            settings, stack.ssm, self.config, self.options, separation=separation
        )
        self.separation = self.governor_model.separation
        law = self.governor_model.law
        ssm = dataclasses.replace(stack.ssm, t_reaction_s=self.reaction_time_s)  # with this system's T_r
        computer = BackupComputer(
            stack.planner,
            stack.make_trajectory,
            stack.geometry,
            deadline_s=self.config.deadline_s,
            workers=self.config.planner_workers,
            timer=timer,
            profile_window_s=self.config.profile_window_s,
            timing=self.governor_model if settings.ssm_timing else None,
        )
        self.jobs = jobs_factory(computer, self.config)

        robot_state = robot.state()
        self.supervisor = Supervisor(
            planner=stack.planner,
            geometry=stack.geometry,
            jobs=self.jobs,
            make_trajectory=stack.make_trajectory,
            separation=self.separation,
            speed_scale=law,
            config=self.config,
            q0=robot_state.q,
            t0=t0,
            on_event=self._emit_abs,
            timer=timer,
            pfl=self.pfl,
            approach_floor_mps=approach_floors(settings, self.pfl),
            timing=self.governor_model if settings.ssm_timing else None,
        )
        self.task = TaskExecutive(
            stack.cell,
            seed=seed,
            pick_dwell_s=self.options.pick_dwell_s,
            place_dwell_s=self.options.place_dwell_s,
            goals=stack.goal_names(),
            chooser=self._choose_station if settings.station_choice == "forecast" else None,
        )
        # where the robot releases each block (world, m)
        self._stations = {st.name: np.asarray(st.xyz, dtype=np.float64) for st in stack.cell.drop_stations}
        # the person's capsules that admit no contact (the station choice keeps the robot away from them)
        self._no_contact = (
            np.asarray(self.pfl.transient_mps, dtype=np.float64) <= 0.0
            if self.pfl.enabled
            else np.ones(len(self.pfl.regions), dtype=bool)
        )
        self.anticipation: FetchAnticipation | None = None
        if method == "proactive" and settings.anticipate_fetch:
            self.anticipation = FetchAnticipation(
                self._stations,
                FetchAnticipationParams(reaction_s=settings.fetch_reaction_s),
                exact_horizon=predictor is not None and predictor.exact_within_horizon,
            )
        self.monitor: GroundTruthMonitor | None = None
        if self.options.monitor:
            from app.planning.collision import HUMAN_CAPSULES, ROBOT_LINKS

            self.monitor = GroundTruthMonitor(
                stack.geometry,
                ssm,
                part_names=ROBOT_LINKS,
                human_capsules=HUMAN_CAPSULES,
                reaction_time_s=self.reaction_time_s,
                pfl=self.pfl,
            )
        self.truth = truth
        self._truth_prev: tuple[float, HumanFrame] | None = None
        #: every person in the cell, followed from capture to capture (:mod:`app.control.people`)
        self.people = People(
            predictor if method == "proactive" else None, PeopleOptions(hold_s=settings.stale_timeout_s)
        )
        self._work_spot = np.asarray(stack.cell.operator.work_spot, dtype=np.float64)
        self.intrusions = 0
        self.completed_tasks = 0
        self.min_separation_m = math.inf
        self.finished: tuple[TrialStatus, str] | None = None
        self.last_frame: HumanFrame | None = None
        self.last_forecast: HumanForecast | None = None
        self.last_decision: FrameDecision | None = None
        self.last_state: RobotState = robot_state
        #: The supervisor's command of the last servo tick (None before the first).
        self.last_command: TickCommand | None = None
        self._recent: deque[HumanFrame] = deque(maxlen=16)  # for the monitor's speed window
        self._releases: list[tuple[float, str]] = []
        self._stale = False
        self._frames_t: list[float] = []
        self._frames_q: list[np.ndarray] = []
        self._frames_sk: list[np.ndarray] = []
        self._frames_ids: list[tuple[int, ...]] = []
        self.decide_s: list[float] = []
        self.frame_to_decision_s = 0.0
        self._fetcher_id: int | None = None
        self._new_stops: set[int] = set()  # the new bodies near the robot that stopped it
        if predictor is not None:
            predictor.reset()
        self._emit_abs(t0, "trial_started", {"method": method, "seed": self.seed})
        self.supervisor.begin(t0)
        self.supervisor.set_goal(self.task.current.goal, not_before=t0)

    def _choose_station(self, allowed: list[str]) -> str:
        """The drop station for the block in the gripper (``Settings.station_choice="forecast"``): of the
        stations the round allows, the one farthest from the person over the method's latest forecast (the
        proactive one, or the reactive method's held pose): the least, over the forecast's steps, of the
        surface distance from the robot's capsules at the station and at its approach pose to the person's
        capsules that admit no contact (skull, face and neck with power and force limiting, where the speed
        governor holds a part at ``S_p`` whatever its speed; every capsule with SSM alone), less the step's
        margin. Ties (and no forecast yet) keep the round's order."""
        forecast = self.last_forecast
        if forecast is None:
            return allowed[0]
        collision = self.stack.collision
        a, b, r = collision.human_capsules(np.asarray(forecast.joints, dtype=np.float64))  # (K, B*M, 3)
        hard = np.tile(self._no_contact, a.shape[1] // self._no_contact.shape[0])
        a, b, r = a[:, hard], b[:, hard], r[hard]
        margins = np.asarray(forecast.margins, dtype=np.float64)  # (K,)
        roadmap = self.stack.roadmap

        q_now = np.asarray(self.last_state.q, dtype=np.float64)

        def pose(node: int) -> np.ndarray:  # the node's usable IK branch nearest the arm now
            branches = np.asarray(roadmap.ik[node], dtype=np.float64)[np.asarray(roadmap.valid[node])]
            wrapped = np.angle(np.exp(1j * (branches - q_now)))  # joint differences in [-pi, pi]
            return branches[int(np.argmin(np.abs(wrapped).sum(axis=1)))]

        def clearance(name: str) -> float:
            nodes = (roadmap.station_nodes[name], roadmap.station_nodes[f"{name}_approach"])
            ra, rb, rr = collision.robot_capsules(np.stack([pose(n) for n in nodes]))  # (2, L, 3)
            d = segment_distance(
                ra[None, :, :, None], rb[None, :, :, None], a[:, None, None], b[:, None, None]
            )  # (K, 2, L, Mh)
            d = d - rr[None, None, :, None] - r[None, None, None, :]
            return float((d.min(axis=(1, 2, 3)) - margins).min())

        return max(allowed, key=clearance)

    # ---------------------------------------------------------------------------------------------------
    def _emit_abs(self, t: float, kind: str, payload: dict[str, Any]) -> None:
        if getattr(self, "finished", None) is not None:
            return
        payload = {  # times in payloads are trial times too
            k: (v - self.t0 if k in _TIME_KEYS and isinstance(v, (int, float)) else v)
            for k, v in payload.items()
        }
        ev = TrialEvent(t=max(float(t) - self.t0, 0.0), kind=kind, payload=_json_safe(payload))
        self.events.append(ev)
        if self.on_event is not None:
            try:
                self.on_event(ev)
            except Exception:
                log.exception("an event listener raised; the trial goes on")

    @property
    def running(self) -> bool:
        return self.finished is None

    def elapsed(self, t: float) -> float:
        return max(float(t) - self.t0, 0.0)

    # ---------------------------------------------------------------------------------------------------
    def frame_tick(self, t: float) -> FrameDecision | None:
        """Read the source at ``t``; a new valid frame goes through the predictor and the supervisor."""
        if self.finished is not None:
            return None
        # the frame goes before the planner pool's jobs until its decision (ForegroundGate, live)
        with self.jobs.foreground():
            tracked = self.source.poll(t)
            if tracked is None:
                return None
            # the frame's time in the software starts when the source handed it over (the time the source
            # takes to make it, a simulated person's or a tracker's own, is not the software's)
            c0 = self.source.handed_over
            people = self.people.update(tracked)
            frame = people.frame  # every body seen, and the lost ones held, with their track ids
            seen = people.seen  # the bodies of this capture alone
            self._check_intrusion(t, people)
            # the bodies as the geometry sees them: the hand capsules out to the fingertips (the predictor
            # keeps the tracked joints it was trained on)
            body = dataclasses.replace(frame, joints=reach_fingertips(frame.joints))
            # the reactive method's forecast: the people held still where they are now; the proactive method
            # weighs the plan it gives as a candidate against its own at every backup
            margin = self.options.tracking_margin_m + self.options.plan_margin_m
            held = self.people.held(people, body, margin_m=margin)
            forecast = held
            if self.method == "proactive":
                self._fetcher_id = self._fetcher(seen)
                if self.predictor.whole_frame:  # a predictor of every body at once (the oracle)
                    forecast = self.predictor.update(seen)
                else:
                    forecast = self.people.forecast(
                        people,
                        margin_m=self.options.tracking_margin_m,
                        shape=self._shape,
                        first=self._fetcher_id,
                    )
                forecast = dataclasses.replace(forecast, joints=reach_fingertips(forecast.joints))
                if self.options.plan_margin_m > 0:
                    extra = self.options.plan_margin_m
                    forecast = dataclasses.replace(forecast, margins=forecast.margins + extra)
            candidate = held if self.settings.reactive_candidate else None
            decision = self.supervisor.on_frame(
                body, forecast, t_now=t, candidate=candidate, ages_s=people.ages_s
            )
            self.decide_s.append(decision.decide_s)
            self.frame_to_decision_s = time.perf_counter() - c0  # validation, people, prediction, decision
        self.people.catch_up()  # the other people's predictors take the capture, for the next decision
        self.last_decision = decision
        sep = decision.separation_m + self.config.tracking_margin_m
        self.min_separation_m = min(self.min_separation_m, sep)
        self.last_forecast = forecast
        self.last_frame = body
        self._recent.append(body)
        if self.options.record_frames:
            self._frames_t.append(self.elapsed(t))
            self._frames_q.append(np.asarray(self.last_state.q, dtype=np.float32))
            self._frames_ids.append(seen.body_ids)
            self._frames_sk.append(np.asarray(seen.joints, dtype=np.float32))
        return decision

    def _shape(self, body: HumanFrame, forecast: HumanForecast) -> HumanForecast:
        """A body's forecast as the task shapes it: the person who will fetch the block the robot has placed
        (:meth:`_fetcher`) is expected to reach for it (:class:`FetchAnticipation`)."""
        if self.anticipation is None or body.body_ids[0] != self._fetcher_id:
            return forecast
        return self.anticipation.apply(body, forecast)

    def _fetcher(self, frame: HumanFrame) -> int | None:
        """The track id of the person expected to fetch the next block: the one whose hand is nearest the
        station the fetch is expected at; with none expected, the one nearest the operator's work spot (over
        the floor). None without a body."""
        if frame.bodies == 0:
            return None
        if frame.bodies == 1:
            return frame.body_ids[0]
        poses = frame.joints.reshape(frame.bodies, -1, 3)
        expected = [] if self.anticipation is None else self.anticipation.expected()
        if expected:
            hands = poses[:, [JOINT_INDEX["l_hand"], JOINT_INDEX["r_hand"]]]
            d = np.linalg.norm(hands - self._stations[expected[0]], axis=-1).min(axis=1)
        else:
            d = np.linalg.norm(poses[:, JOINT_INDEX["pelvis"], :2] - self._work_spot[:2], axis=1)
        return frame.body_ids[int(np.argmin(d))]

    def _check_intrusion(self, t: float, people: PeopleUpdate) -> None:
        """A body that moved faster than a person can since the last capture (or the tracker jumped to
        someone else), or a new body near the robot before it has been tracked long enough to forecast: a
        protective stop, and that body's forecast starts over."""
        for tid in people.appeared:
            self._emit_abs(t, "body_appeared", {"body": tid})
        for tracker_id, tid in people.renamed.items():
            self._emit_abs(t, "body_renamed", {"body": tid, "tracker_id": tracker_id})
        for tid in people.dropped:
            self._emit_abs(t, "body_dropped", {"body": tid})
            self._new_stops.discard(tid)
        near = self._new_near(people)
        if near is not None:  # held at every frame until it has settled; counted once
            if near[0] not in self._new_stops:
                self._new_stops.add(near[0])
                self.intrusions += 1
                log.warning("intrusion: a new body %d within %.2f m of the robot; protective stop", *near)
                self._emit_abs(t, "intrusion", {"body": near[0], "separation_m": near[1]})
            self.supervisor.intrusion(t)
            self._recent.clear()
            return
        # a body that moved faster than a person can (the validated source's check, by tracker id)
        jumped = [(self.people.track_id(i), v) for i, v in self.source.last_changes.jumps.items()]
        jumped = [(tid, v) for tid, v in jumped if tid is not None]
        if not jumped:
            return
        tid, speed = max(jumped, key=lambda j: j[1])
        self.intrusions += 1
        log.warning("intrusion: a person moved at %.1f m/s between two frames; protective stop", speed)
        self._emit_abs(t, "intrusion", {"speed_mps": speed, "body": tid})
        self.supervisor.intrusion(t)
        self._recent.clear()
        if self.predictor is not None:
            self.people.reset_forecast([j[0] for j in jumped])

    def _new_near(self, people: PeopleUpdate) -> tuple[int, float] | None:
        """A settling body (new, not yet forecast) within ``near_m`` of the robot: its track id and its
        distance (m); None if there is none."""
        if not people.settling:
            return None
        frame, q = people.frame, np.asarray(self.last_state.q, dtype=np.float64)
        collision = self.stack.collision
        for k, tid in enumerate(frame.body_ids):
            if tid not in people.settling:
                continue
            d = float(collision.distance_to_human(q[None], frame.body(k).joints[None])[0, 0])
            if d < self.people.options.near_m:
                return tid, d
        return None

    def _judge(self, t: float, state: RobotState) -> None:
        """The ground-truth monitor's check of this servo tick."""
        mon = self.monitor
        assert mon is not None
        if self.truth is not None:
            truth = self.truth(t)
            now = (
                truth if isinstance(truth, HumanFrame) else HumanFrame(t, np.asarray(truth, dtype=np.float64))
            )
            now = dataclasses.replace(now, t=t, joints=reach_fingertips(now.joints))
            prev = self._truth_prev
            joints = now.joints
            before, dt = (joints, 0.0) if prev is None else (now.matched(prev[1]), t - prev[0])
            entered = prev is not None and not set(now.body_ids) <= set(prev[1].body_ids)
            self._truth_prev = (t, now)
        else:  # no truth (a real cell): the tracker's frames are the best there is
            frame = self.last_frame
            if frame is None:
                return
            old = self._older_frame(frame)
            joints = frame.joints
            before, dt = (joints, 0.0) if old is None else (frame.matched(old), frame.t - old.t)
            entered = old is not None and not set(frame.body_ids) <= set(old.body_ids)
        violations, contacts, harmful_before = mon.violations, mon.contacts, mon.harmful_contacts
        sample = mon.check(t, state.q, state.qd, joints, before, dt, entered=entered)
        if mon.violations > violations:
            log.error(
                "safety monitor: %s at %.3f m < S_p %.3f m",
                sample.part,
                sample.separation_m,
                sample.required_m,
            )
            payload = sample.to_json()
            payload.pop("t")
            self._emit_abs(t, "violation", payload)
        harmful = mon.harmful_contacts > harmful_before
        if mon.contacts > contacts or harmful:
            (log.error if harmful else log.info)(
                "safety monitor: %s contact of %s with the %s at %.2f m/s toward it (permissible %.2f)",
                "harmful" if harmful else "permitted",
                sample.part,
                sample.region,
                sample.robot_speed_mps,
                sample.permissible_mps,
            )
            self._emit_abs(
                t,
                "contact",
                {
                    "part": sample.part,
                    "region": sample.region,
                    "harmful": harmful,
                    "separation_m": sample.separation_m,
                    "robot_speed_mps": sample.robot_speed_mps,
                    "permissible_mps": sample.permissible_mps,
                },
            )

    def _older_frame(self, frame: HumanFrame) -> HumanFrame | None:
        """The frame the person's approach speed is measured from: the newest one at least the speed window
        (the supervisor's, 0.1 s) before ``frame``, else the oldest one before it."""
        window = self.config.human_speed_window_s
        older = [f for f in self._recent if f.t < frame.t]
        for f in reversed(older):
            if f.t <= frame.t - window + 1e-9:
                return f
        return older[0] if older else None

    def servo_tick(self, t: float) -> None:
        """One robot cycle at ``t``: read the robot, advance the supervisor, command it, do the task."""
        if self.finished is not None:
            return
        try:
            state = self.robot.state()
        except RobotConnectionError as exc:
            self._robot_lost(t, str(exc))
            return
        if not state.connected:
            self._robot_lost(t, f"robot disconnected ({getattr(state, 'fault', None) or 'no reason given'})")
            return
        self.last_state = state
        if self.monitor is not None:
            self._judge(t, state)
        stale = self.source.is_stale(t)
        if stale != self._stale:
            self._stale = stale
            self.supervisor.set_stale(stale, t)
        cmd = self.supervisor.servo(t)
        self.last_command = cmd
        q_cmd = cmd.q
        if cmd.halted and float(np.abs(state.q - cmd.q).max()) <= _HALT_TOLERANCE_RAD:
            # halted part of the way: stay where the arm is, not creep on to the command it lags by a few
            # milliradians (the arm would be moving, slowly, while the governor holds it)
            q_cmd = np.asarray(state.q, dtype=np.float64)
        if not self.supervisor.estopped:  # after an E-stop nothing is commanded until reset
            try:
                self.robot.servo(q_cmd, cmd.qd, t)
            except RobotConnectionError as exc:
                self._robot_lost(t, str(exc))
                return
        goal = self.supervisor.take_arrival()
        if goal is not None:
            done = self.task.arrived(t)
            if done.placed is not None:
                self._releases.append((done.leave_at, done.placed))
                if self.anticipation is not None:
                    self.anticipation.expect(done.placed, done.leave_at)
            self.supervisor.set_goal(done.next_leg.goal, not_before=done.leave_at)
        elif self.settings.reroute_after_s is not None:
            self._maybe_reroute(t, self.settings.reroute_after_s)
        while self._releases and self._releases[0][0] <= t:
            _, station = self._releases.pop(0)
            self.completed_tasks += 1
            self._emit_abs(t, "task_completed", {"station": station, "index": self.completed_tasks})
            self.source.notify_block_placed(station, t)
        if self.elapsed(t) >= self.duration_s - 1e-9:
            self.finish(t, "completed", "duration")

    def _maybe_reroute(self, t: float, after_s: float) -> None:
        """A robot held still ``after_s`` on its way to a drop station that the person blocks takes its
        block to the freest other station of the round (``Settings.reroute_after_s``)."""
        if self.supervisor.still_for(t) < after_s:
            return
        others = self.task.drop_alternatives()
        if not others:
            return
        station = self._choose_station(others)
        if self.supervisor.reroute(self.task.reroute_goal(station), t):
            self.task.reroute(station)

    def _robot_lost(self, t: float, message: str) -> None:
        log.error("robot connection lost: %s; the trial is aborted", message)
        self.supervisor.fault(t, message)
        self.finish(t, "aborted", "robot_fault")

    def estop(self, t: float, *, source: str) -> None:
        self.supervisor.estop(t, source=source)

    def finish(self, t: float, status: TrialStatus, reason: str) -> None:
        """End the trial (idempotent)."""
        if self.finished is not None:
            return
        self.supervisor.end(t)
        self._emit_abs(t, "trial_ended", {"status": status, "reason": reason})
        self.finished = (status, reason)  # from here on no more events
        self.jobs.close()
        self._end_t = float(t)

    # ---------------------------------------------------------------------------------------------------
    def metrics(self) -> TrialMetrics:
        c = self.supervisor.counters
        times = np.asarray(c.planning_times_s, dtype=np.float64)
        end_t = getattr(self, "_end_t", self.supervisor.status().t)
        st = c.state_time_s
        counters = self.source.counters
        mon = self.monitor
        arrivals = self.arrival_error()
        return TrialMetrics(
            method=self.method,
            duration_s=round(self.elapsed(end_t), 6),
            completed_tasks=self.completed_tasks,
            plans_computed=c.plans_computed,
            avg_planning_time_s=float(times.mean()) if times.size else 0.0,
            p95_planning_time_s=float(np.percentile(times, 95)) if times.size else 0.0,
            stop_replans=c.stop_replans,
            stop_replans_moving=c.stop_replans_moving,
            online_replans=c.online_replans,
            deadline_misses=c.deadline_misses,
            emergency_plans=c.emergency_plans,
            plan_failures=c.plan_failures,
            min_separation_m=self.min_separation_m,
            violations=0 if mon is None else mon.violations,
            contacts=0 if mon is None else mon.contacts,
            violation_time_s=0.0 if mon is None else round(mon.violation_time_s, 6),
            violations_iso=0 if mon is None else mon.violations_iso,
            violations_person_faster=0 if mon is None else mon.violations_person_faster,
            harmful_contacts=0 if mon is None else mon.harmful_contacts,
            violations_measured_vh=0 if mon is None else mon.violations_measured_vh,
            exceedance_s=0.0 if mon is None else round(mon.exceedance_s, 6),
            max_approach_mps=0.0 if mon is None else round(mon.max_approach_mps, 4),
            intrusions=self.intrusions,
            min_separation_moving_m=math.inf if mon is None else mon.min_separation_moving_m,
            time_stopped_s=st["stopped"] + st["estop"] + st["fault"],
            time_nominal_s=st["nominal"],
            time_collision_avoidance_s=st["collision_avoidance"],
            time_moving_s=c.moving_time_s,
            mean_speed_scale=c.scale_time_s / c.moving_time_s if c.moving_time_s > 0 else 0.0,
            **{f"budget_{k}_s": round(v, 6) for k, v in c.budget_s.items()},
            arrivals=int(arrivals["n"] or 0),
            arrival_error_median_abs_s=_nan_if_none(arrivals["median_abs"]),
            arrival_error_bias_s=_nan_if_none(arrivals["bias"]),
            median_plan_s=_nan_if_none(arrivals["median_plan_s"]),
            plans_forecast=c.plan_choices["forecast"],
            plans_reactive=c.plan_choices["reactive"],
            plans_reactive_only=c.plan_choices["reactive_only"],
            reactive_gain_s=round(c.reactive_gain_s, 6),
            stale_stops=c.stale_stops,
            frames_received=int(counters.get("accepted", 0)) + int(counters.get("rejected", 0)),
            frames_rejected=int(counters.get("rejected", 0)),
        )

    def time_budget(self) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
        """Where the trial's time went, from one copy of the supervisor's counters (the two agree):

        - seconds per :data:`app.control.supervisor_types.TIME_BUDGET` part (they sum to the trial's
          duration), and ``mean_scale_when_scaled``, the mean speed scale over ``moving_scaled``;
        - the same per task pose: for each goal the robot headed for (or waited to leave for; the gripper's
          dwell counts under the pose where it grips or releases, ``"none"`` is time without a goal), the
          seconds per part spent on it (parts with none left out) and their ``total``, the goals in order of
          total, largest first. Summed over the goals, each part is the trial's. It shows where the cell
          loses its time: a task pose the person's hands keep inside the speed governor's zone (``hrc cell
          check``) holds the robot still there.
        """
        budget, by_goal, scale_s = self.supervisor.time_budget()
        out = {k: round(v, 4) for k, v in budget.items()}
        scaled = budget["moving_scaled"]
        out["mean_scale_when_scaled"] = round(scale_s / scaled, 4) if scaled > 0 else 0.0
        rows = []
        for goal, parts in by_goal.items():
            kept = {k: round(v, 4) for k, v in parts.items() if v > 0}
            rows.append((goal, kept | {"total": round(sum(parts.values()), 4)}))
        rows.sort(key=lambda r: -r[1]["total"])
        return out, dict(rows)

    def arrival_error(self) -> dict[str, float | int | None]:
        """Each plan's predicted arrival against the executed one, over the plans that reached their goal:
        ``median_abs`` and ``bias`` (executed minus predicted, s; positive: late), ``n``, and the median plan
        duration (s) to compare them with."""
        arrivals = np.asarray(self.supervisor.counters.arrivals, dtype=np.float64).reshape(-1, 2)
        if arrivals.shape[0] == 0:
            return {"n": 0, "median_abs": None, "bias": None, "median_plan_s": None}
        err = arrivals[:, 1]
        return {
            "n": int(err.size),
            "median_abs": round(float(np.median(np.abs(err))), 4),
            "bias": round(float(np.mean(err)), 4),
            "median_plan_s": round(float(np.median(arrivals[:, 0])), 4),
        }

    def frames(self, start: int = 0) -> TrialFrames | None:
        """The recorded frames from index ``start`` on (None when none are recorded there). Safe to call
        from another thread while the frame thread records: it takes the frames all three lists hold."""
        if not self.options.record_frames:
            return None
        n = min(len(self._frames_t), len(self._frames_q), len(self._frames_ids), len(self._frames_sk))
        if n <= start:
            return None
        skeleton, body_ids = pad_bodies(self._frames_sk[start:n], self._frames_ids[start:n])
        return TrialFrames(
            t=np.asarray(self._frames_t[start:n], dtype=np.float64),
            q=np.stack(self._frames_q[start:n]),
            skeleton=skeleton,
            body_ids=body_ids,
        )

    def counters(self) -> dict[str, Any]:
        c = self.supervisor.counters
        return {
            "completed_tasks": self.completed_tasks,
            "stop_replans": c.stop_replans,
            "online_replans": c.online_replans,
            "deadline_misses": c.deadline_misses,
            "emergency_plans": c.emergency_plans,
            "plan_failures": c.plan_failures,
            "plans_computed": c.plans_computed,
            "frames": c.frames,
            "violations": 0 if self.monitor is None else self.monitor.violations,
            "contacts": 0 if self.monitor is None else self.monitor.contacts,
            "intrusions": self.intrusions,
            "min_separation_m": self.min_separation_m,
        }


def _nan_if_none(v: float | int | None) -> float:
    return math.nan if v is None else float(v)


def make_validated_source(
    source: Any, cell: WorkCell, *, stale_timeout_s: float = 0.35, jump_speed_mps: float = 5.0
) -> ValidatedSource:
    """``source`` behind the cell's frame checks and a stale watchdog (``Settings.stale_timeout_s``; a
    :class:`ValidatedSource` is returned as it is); a body that moves faster than ``jump_speed_mps``
    between two frames jumped (:attr:`EngineOptions.intrusion_speed_mps`)."""
    if isinstance(source, ValidatedSource):
        return source
    watchdog = StaleWatchdog(stale_timeout_s)
    validator = FrameValidator.for_workcell(cell, jump_speed_mps=jump_speed_mps)
    return ValidatedSource(source, validator=validator, watchdog=watchdog)


_TIME_KEYS = frozenset({"t_switch", "violation_t"})


def _json_safe(payload: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in payload.items():
        if isinstance(v, (np.floating, float)):
            v = float(v)
            out[k] = v if math.isfinite(v) else None
        elif isinstance(v, np.integer):
            out[k] = int(v)
        elif isinstance(v, np.ndarray):
            out[k] = v.tolist()
        else:
            out[k] = v
    return out


__all__ = [
    "CellGeometry",
    "EngineOptions",
    "PlanningStack",
    "Snapshot",
    "TrialEngine",
    "TrialFrames",
    "TrialResult",
    "make_validated_source",
]
