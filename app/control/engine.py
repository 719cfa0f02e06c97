"""One trial's wiring, shared by the live runtime and the headless runner:
source -> validation -> predictor -> supervisor -> trajectory -> robot, plus the task, metrics and events.
The proactive method's forecast also expects the person to fetch each block the robot places
(:mod:`app.control.anticipation`, ``Settings.anticipate_fetch``).

:class:`TrialEngine` has no threads and no clock of its own: the caller invokes
:meth:`TrialEngine.frame_tick` at the camera rate and :meth:`TrialEngine.servo_tick` at the robot
rate with the current time (the live runtime from its threads on the wall clock, the headless runner
from one loop on the simulated clock).

Also here: :class:`PlanningStack` (kinematics, collision model, roadmap and planner, built once per
work cell) and :class:`CellGeometry` (the supervisor's and the monitor's view of the robot's body).

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
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from app.cell.robot import RobotBackend, RobotConnectionError, RobotState
from app.cell.validation import FrameValidator, StaleWatchdog, ValidatedSource
from app.config import Settings, WorkCell
from app.control.anticipation import FetchAnticipation, FetchAnticipationParams
from app.control.backup import BackupComputer, PlanJobs
from app.control.metrics import Method, TrialEvent, TrialMetrics
from app.control.supervisor import FrameDecision, Supervisor, SupervisorConfig
from app.control.task import TaskExecutive
from app.planning.collision import reach_fingertips
from app.planning.ssm_timing import part_speeds
from app.prediction.forecast import HumanForecast, Predictor
from app.prediction.skeleton import HumanFrame
from app.safety.governor import GovernorModel, SeparationModel, SpeedScaleLaw, directed_approach
from app.safety.modes import PartMode, binding_part, mode_text, region_text
from app.safety.monitor import GroundTruthMonitor, MonitorTotals, is_intrusion
from app.safety.pfl import PFLModel
from app.safety.stopping import UR5E_STOP

log = logging.getLogger(__name__)

TrialStatus = Literal["completed", "aborted"]

#: The directed speed (m/s) that the supervisor measures on a still person, per metre of tracker noise per
#: joint and axis over its speed window: for the SSM-aware timing's prediction of the governor
#: (:class:`app.safety.governor.GovernorModel.speed_noise_mps`). Tuned on seeds 1000-1003: the median of the
#: measured directed speed of the simulated operator at work, 0.33 m/s with 1 cm of noise over 0.1 s.
SPEED_NOISE_GAIN = 3.3


# --------------------------------------------------------------------------------------------------------
# The planning stack and the robot's geometry
# --------------------------------------------------------------------------------------------------------


class CellGeometry:
    """The UR5e's body as parts, one per capsule of the collision model (the supervisor's
    :class:`~app.control.trajectory_views.RobotGeometry`).

    A part's speed is that of the faster end of its capsule's axis: on a rigid link every point of the axis
    moves no faster than that, so it bounds the speed of the capsule's whole surface.
    """

    def __init__(self, collision: Any, *, fd_step_s: float = 1e-3) -> None:
        self.collision = collision
        self.fd_step_s = float(fd_step_s)

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(P, L, M) surface distance (m) of each robot part at ``q`` (6,) to each capsule of the person in
        poses (P, J, 3) (:meth:`app.planning.collision.CollisionModel.pair_distances`, which checks the
        shapes)."""
        return self.collision.pair_distances(np.asarray(q, dtype=np.float64).reshape(6), joints)

    def part_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(P, L) surface distance (m) of each robot part at ``q`` (6,) to the person in poses (P, J, 3)."""
        return self.pair_distances(q, joints).min(axis=2)

    def near_person(
        self, q: np.ndarray, joints: np.ndarray, joints_before: np.ndarray, dt_s: float, *, band_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each part's separation (L,) to the person at ``joints`` and the person's *directed* speed (L,)
        toward it since ``joints_before``, ``dt_s`` earlier
        (:func:`app.safety.governor.directed_approach`)."""
        poses = np.stack([np.asarray(joints, dtype=np.float64), np.asarray(joints_before, dtype=np.float64)])
        d = self.pair_distances(q, poses)  # (2, L, M)
        return directed_approach(d[0], d[1], dt_s, band_m=band_m)

    def human_static_gaps(self, joints: np.ndarray, capsules: np.ndarray | None = None) -> np.ndarray:
        """(M,) each of the person's capsules' gap (m) to the static scene, inf but for ``capsules``
        (:meth:`app.planning.collision.CollisionModel.human_static_gaps`)."""
        return self.collision.human_static_gaps(joints, capsules)

    def path_separations(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        """(K, L) surface distance (m) of each part of the robot at each of ``q`` (K, 6) to the person at
        ``joints`` (J, 3)."""
        q = np.asarray(q, dtype=np.float64).reshape(-1, 6)
        poses = np.broadcast_to(np.asarray(joints, dtype=np.float64), (q.shape[0], *np.shape(joints)))
        segments = self.collision.robot_segments(q)
        n_parts = segments[0].shape[0]
        return np.stack(
            [
                self.collision.distance_to_human_paired(q, poses, segments=segments, links=np.array([i]))
                for i in range(n_parts)
            ],
            axis=1,
        )

    def separation(self, q: np.ndarray, joints: np.ndarray) -> float:
        """Minimum surface distance (m) robot-person for ``q`` (6,) and ``joints`` (J, 3)."""
        return float(self.part_separations(q, np.asarray(joints)[None]).min())

    def part_speeds(self, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
        """(K, L) speed (m/s) of each part for ``q``, ``qd`` (K, 6)
        (:func:`app.planning.ssm_timing.part_speeds`)."""
        return part_speeds(self.collision, q, qd, fd_step_s=self.fd_step_s)


@dataclass(frozen=True)
class PlanningStack:
    """Everything that is built once per work cell: kinematics, collision model, roadmap, planner.

    Build it with :meth:`for_cell` (cached per process and cell).
    """

    cell: WorkCell
    kin: Any
    collision: Any
    roadmap: Any
    planner: Any
    geometry: CellGeometry
    ssm: Any

    @classmethod
    def for_cell(
        cls, cell: WorkCell, *, t_reaction_s: float | None = None, cache_dir: str | Path | None = None
    ) -> PlanningStack:
        """The stack of ``cell`` (roadmap from the on-disk cache, built when missing), its planner's clearance
        with the reaction time ``t_reaction_s`` of the installation
        (:meth:`app.config.Settings.reaction_time_s`: the ``T_r`` of the governor and the monitor; default
        :class:`app.safety.ssm.SSMParams`'). Cached per process, cell and ``T_r``."""
        key = (cell.fingerprint(), None if cache_dir is None else str(cache_dir), t_reaction_s)
        with _STACK_LOCK:
            stack = _STACKS.get(key)
            if stack is None:
                stack = _build_stack(cell, key[1], t_reaction_s=t_reaction_s)
                _STACKS[key] = stack
                while len(_STACKS) > 4:
                    _STACKS.pop(next(iter(_STACKS)))
            return stack

    @classmethod
    def build(
        cls,
        cell: WorkCell,
        *,
        roadmap_config: Any | None = None,
        planner_config: Any | None = None,
        t_reaction_s: float | None = None,
        cache_dir: str | Path | None = None,
    ) -> PlanningStack:
        """A new stack (not cached in the process) with explicit roadmap and planner settings
        (:class:`app.planning.roadmap.RoadmapConfig`, :class:`app.planning.search.PlannerConfig`);
        ``t_reaction_s`` replaces the planner settings' ``T_r`` (see :meth:`for_cell`)."""
        return _build_stack(
            cell,
            None if cache_dir is None else str(cache_dir),
            roadmap_config=roadmap_config,
            planner_config=planner_config,
            t_reaction_s=t_reaction_s,
        )

    def with_reaction_time(self, t_reaction_s: float) -> PlanningStack:
        """This stack with its planner's clearance at the reaction time ``t_reaction_s`` (``T_r``; see
        :meth:`for_cell`): a new planner on the same roadmap and collision model, or this stack when it has
        that ``T_r`` already."""
        from app.planning.search import Planner

        if math.isclose(self.ssm.t_reaction_s, t_reaction_s, rel_tol=0.0, abs_tol=1e-9):
            return self  # the tolerance of TrialEngine's check of the stack's T_r
        config = self.planner.config.with_reaction_time(t_reaction_s)
        planner = Planner(self.roadmap, self.collision, config=config)
        return dataclasses.replace(self, planner=planner, ssm=config.ssm)

    def make_trajectory(self, plan: Any, qd0: np.ndarray | None) -> Any:
        from app.planning.trajectory import Trajectory

        return Trajectory.from_plan(plan, qd0=qd0, kin=self.kin)

    def goal_names(self) -> list[str]:
        return list(self.roadmap.station_nodes)


_STACKS: dict[tuple[str, str | None, float | None], PlanningStack] = {}
_STACK_LOCK = threading.Lock()


def _build_stack(
    cell: WorkCell,
    cache_dir: str | None,
    *,
    roadmap_config: Any | None = None,
    planner_config: Any | None = None,
    t_reaction_s: float | None = None,
) -> PlanningStack:
    from app.planning.collision import CollisionModel
    from app.planning.roadmap import load_or_build_roadmap
    from app.planning.search import Planner, PlannerConfig

    t0 = time.perf_counter()
    collision = CollisionModel(cell)
    roadmap = load_or_build_roadmap(cell, config=roadmap_config, cache_dir=cache_dir, collision=collision)
    config = planner_config or PlannerConfig()
    if t_reaction_s is not None:
        config = config.with_reaction_time(t_reaction_s)
    planner = Planner(roadmap, collision, config=config)
    log.info("planning stack for cell %s ready in %.2f s", cell.name, time.perf_counter() - t0)
    return PlanningStack(
        cell=cell,
        kin=collision.kin,
        collision=collision,
        roadmap=roadmap,
        planner=planner,
        geometry=CellGeometry(collision),
        ssm=config.ssm,
    )


# --------------------------------------------------------------------------------------------------------
# Messages: snapshots and trial results
# --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TrialFrames:
    """A trial's frames at the camera rate (the study database's recorded frames).

    Attributes:
        t: (T,) seconds since the trial started.
        q: (T, 6) robot joint positions (rad).
        skeleton: (T, J, 3) person joints in the world frame (m), or None when none were recorded.
    """

    t: np.ndarray
    q: np.ndarray
    skeleton: np.ndarray | None

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass(frozen=True, slots=True)
class TrialResult:
    """What one trial produced.

    Attributes:
        metrics: The trial's metrics.
        events: Its events, in time order (``t`` = seconds since the trial started).
        frames: Its frames (None when not recorded).
        status: ``completed`` (ran its duration) or ``aborted``.
        reason: Why it ended (``duration``, ``operator``, ``estop``, ``robot_fault``, ...).
        wall_s: Wall-clock seconds the run took.
        sim_speedup: Simulated seconds per wall second (headless runs; 1 live).
        safety: The ground-truth monitor's verdict (None when the monitor was off).
        tracker_latency_s: The tracker latency the trial ran with (s; None: unknown, a live tracker).
        time_budget_s: Where the trial's time went (:meth:`TrialEngine.time_budget`).
        time_budget_by_goal_s: The same per task pose (:meth:`TrialEngine.time_budget`).
        arrival_error_s: Predicted against executed arrivals (:meth:`TrialEngine.arrival_error`).
    """

    metrics: TrialMetrics
    events: list[TrialEvent]
    frames: TrialFrames | None
    status: TrialStatus = "completed"
    reason: str = "duration"
    wall_s: float = 0.0
    sim_speedup: float = 1.0
    safety: MonitorTotals | None = None
    tracker_latency_s: float | None = None
    time_budget_s: dict[str, float] | None = None
    arrival_error_s: dict[str, float | int | None] | None = None
    time_budget_by_goal_s: dict[str, dict[str, float]] | None = None

    def _worst_json(self) -> dict[str, Any] | None:
        worst = None if self.safety is None else self.safety.worst
        return None if worst is None else worst.to_json()

    def summary(self) -> dict[str, Any]:
        """The ``hrc simulate --json`` object."""
        m = self.metrics
        return {
            "method": m.method,
            "status": self.status,
            "duration_s": m.duration_s,
            "completed_tasks": m.completed_tasks,
            "avg_planning_time_s": m.avg_planning_time_s,
            "stop_replans_per_task": m.stop_replans_per_task,
            "online_replans_per_task": m.online_replans_per_task,
            "stop_replans": m.stop_replans,
            "stop_replans_moving": m.stop_replans_moving,
            "online_replans": m.online_replans,
            "deadline_misses": m.deadline_misses,
            "plans_computed": m.plans_computed,
            "min_separation_m": None if not math.isfinite(m.min_separation_m) else m.min_separation_m,
            "violations": m.violations,
            "contacts": m.contacts,
            "violation_time_s": m.violation_time_s,
            "violations_iso": m.violations_iso,
            "violations_person_faster": m.violations_person_faster,
            "harmful_contacts": m.harmful_contacts,
            "violations_measured_vh": m.violations_measured_vh,
            "exceedance_s": m.exceedance_s,
            "max_approach_mps": m.max_approach_mps,
            "intrusions": m.intrusions,
            "min_separation_moving_m": (
                None if not math.isfinite(m.min_separation_moving_m) else m.min_separation_moving_m
            ),
            "tracker_latency_s": self.tracker_latency_s,
            "violations_in_intrusions": 0 if self.safety is None else self.safety.violations_in_intrusions,
            "worst_sample": self._worst_json(),
            "violation_episodes": (
                [] if self.safety is None else [e.to_json() for e in self.safety.episodes]
            ),
            "time_budget_s": self.time_budget_s,
            "time_budget_by_goal_s": self.time_budget_by_goal_s,
            "arrival_error_s": self.arrival_error_s,
            "time_stopped_s": m.time_stopped_s,
            "time_moving_s": m.time_moving_s,
            "mean_speed_scale": m.mean_speed_scale,
            "sim_speedup": self.sim_speedup,
        }


@dataclass(frozen=True, slots=True)
class Snapshot:
    """An immutable view of the runtime for viewers (operator page, 3D scene, API).

    Attributes:
        t: Runtime clock (s).
        trial_id: Running trial, or None.
        state: Supervisor state (``idle``, ``nominal``, ``collision_avoidance``, ``stopped``, ``estop``,
            ``fault``).
        method: Method of the running trial, or None.
        speed_scale: Speed scale along the path, 0..1.
        separation_m: The separation (m) of the part that limits the robot from the body regions it keeps
            ``S_p`` from (:attr:`app.control.supervisor_types.SupervisorStatus.separation_m`), None when
            nobody was seen.
        required_separation_m: The separation (m) the speed governor holds that part to at its current
            speed (what it needs to move, where it is stopped).
        planning_ms: Recent backup-plan compute times (ms), oldest first.
        counters: Running counts (completed tasks, replans, deadline misses, frames, ...).
        q: (6,) robot joint positions (rad).
        p_world_tcp: (3,) TCP position (m, world).
        skeleton: (J, 3) latest person pose (m, world), or None.
        forecast: (H, J, 3) latest forecast, or None.
        plan_tcp: (K, 3) TCP path of the plan in execution, or None.
        backup_tcp: (K, 3) TCP path of the pending backup plan, or None.
        stale: The human stream is stale.
        estopped: E-stop latched.
        trial_elapsed_s: Seconds since the trial started, or None.
        trial_duration_s: The trial's planned duration, or None.
        time_budget: Where the running trial's time went so far (:meth:`TrialEngine.time_budget`: seconds
            per part of :data:`app.control.supervisor_types.TIME_BUDGET`, and ``mean_scale_when_scaled``);
            empty without a trial.
        time_budget_by_goal: The same per task pose so far (:meth:`TrialEngine.time_budget`); empty without a
            trial.
        part_modes: What limits each robot part now (:class:`app.safety.modes.PartMode`); empty without a
            trial.
        part_names: The robot parts' names, in the order of ``part_modes``.
    """

    t: float
    trial_id: int | None
    state: str
    method: str | None
    speed_scale: float
    separation_m: float | None
    required_separation_m: float | None
    planning_ms: tuple[float, ...]
    counters: dict[str, Any]
    q: np.ndarray
    p_world_tcp: np.ndarray
    skeleton: np.ndarray | None = None
    forecast: np.ndarray | None = None
    plan_tcp: np.ndarray | None = None
    backup_tcp: np.ndarray | None = None
    stale: bool = False
    estopped: bool = False
    trial_elapsed_s: float | None = None
    trial_duration_s: float | None = None
    time_budget: dict[str, float] = field(default_factory=dict)
    time_budget_by_goal: dict[str, dict[str, float]] = field(default_factory=dict)
    part_modes: tuple[PartMode, ...] = ()
    part_names: tuple[str, ...] = ()

    @property
    def limiting_part(self) -> int:
        """Index of the part that limits the robot (:func:`app.safety.modes.binding_part`; -1: none)."""
        return binding_part(self.part_modes)

    @property
    def mode(self) -> str | None:
        """The robot's mode: the limiting part's (:attr:`app.safety.modes.PartMode.label`), ``stopped``
        under an E-stop, None without a trial. The one field the operator page and the 3D view show."""
        if self.estopped:
            return "stopped"
        k = self.limiting_part
        return None if k < 0 else self.part_modes[k].label

    def part_name(self, i: int) -> str:
        return self.part_names[i] if 0 <= i < len(self.part_names) else f"part {i}"

    def __post_init__(self) -> None:
        for name in ("q", "p_world_tcp", "skeleton", "forecast", "plan_tcp", "backup_tcp"):
            v = getattr(self, name)
            if v is not None:
                a = np.array(v, dtype=np.float64)
                a.setflags(write=False)
                object.__setattr__(self, name, a)
        if self.q.shape != (6,) or self.p_world_tcp.shape != (3,):
            raise ValueError(f"Snapshot q must be (6,) and p_world_tcp (3,), got {self.q.shape}")
        object.__setattr__(self, "counters", dict(self.counters))

    def to_json(self) -> dict[str, Any]:
        """JSON-friendly dict (arrays as nested lists, non-finite floats as None)."""

        def num(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)

        def arr(a: np.ndarray | None, nd: int = 4) -> list | None:
            return None if a is None else np.round(a, nd).tolist()

        return {
            "t": float(self.t),
            "trial_id": self.trial_id,
            "state": self.state,
            "method": self.method,
            "speed_scale": float(self.speed_scale),
            "separation_m": num(self.separation_m),
            "required_separation_m": num(self.required_separation_m),
            "planning_ms": [round(float(x), 3) for x in self.planning_ms],
            "counters": {k: (num(v) if isinstance(v, float) else v) for k, v in self.counters.items()},
            "q": arr(self.q, 5),
            "p_world_tcp": arr(self.p_world_tcp),
            "skeleton": arr(self.skeleton),
            "forecast": arr(self.forecast),
            "plan_tcp": arr(self.plan_tcp),
            "backup_tcp": arr(self.backup_tcp),
            "stale": bool(self.stale),
            "estopped": bool(self.estopped),
            "trial_elapsed_s": num(self.trial_elapsed_s),
            "trial_duration_s": num(self.trial_duration_s),
            "time_budget": {k: round(float(v), 3) for k, v in self.time_budget.items()},
            "time_budget_by_goal": {
                g: {k: round(float(v), 3) for k, v in parts.items()}
                for g, parts in self.time_budget_by_goal.items()
            },
            "mode": self.mode,
            "mode_text": mode_text(self.mode),
            "limiting_part": None if self.limiting_part < 0 else self.part_name(self.limiting_part),
            "parts": [
                {
                    "name": self.part_name(i),
                    "mode": m.mode,
                    "label": m.label,
                    "text": m.text,
                    "region": m.region,
                    "held_from": m.held_from,
                    "held_from_text": None if m.held_from is None else region_text(m.held_from),
                    "separation_m": num(m.separation_m),
                    "required_m": num(m.required_m),
                    "limit_scale": round(float(m.limit_scale), 4),
                }
                for i, m in enumerate(self.part_modes)
            ],
        }


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
        frame_period_s=settings.frame_period_s,
        planner_workers=settings.planner_workers,
        tracking_margin_m=options.tracking_margin_m,
        robot_toward=settings.robot_toward,
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


def pfl_model(settings: Settings) -> PFLModel:
    """The power and force limiting of a trial (:class:`app.safety.pfl.PFLModel`): the person's capsules,
    the UR5e's moving mass and the declared payload; ``enabled`` by ``Settings.pfl``."""
    from app.planning.collision import HUMAN_CAPSULES

    return PFLModel.for_capsules(HUMAN_CAPSULES, payload_kg=settings.pfl_payload_kg, enabled=settings.pfl)


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
        )
        self.task = TaskExecutive(
            stack.cell,
            seed=seed,
            pick_dwell_s=self.options.pick_dwell_s,
            place_dwell_s=self.options.place_dwell_s,
            goals=stack.goal_names(),
            chooser=self._choose_station if settings.station_choice == "forecast" else None,
        )
        # where the robot releases each block (world, m), and its approach pose above it
        self._stations = {st.name: np.asarray(st.xyz, dtype=np.float64) for st in stack.cell.drop_stations}
        self._approach_up = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, stack.cell.approach_height_m]])
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
        self._truth_prev: tuple[float, np.ndarray] | None = None
        self._last_tracked: HumanFrame | None = None  # the last frame as the tracker gave it
        self.intrusions = 0
        self.completed_tasks = 0
        self.min_separation_m = math.inf
        self.finished: tuple[TrialStatus, str] | None = None
        self.last_frame: HumanFrame | None = None
        self.last_forecast: HumanForecast | None = None
        self.last_decision: FrameDecision | None = None
        self.last_state: RobotState = robot_state
        self._recent: deque[HumanFrame] = deque(maxlen=16)  # for the monitor's speed window
        self._releases: list[tuple[float, str]] = []
        self._stale = False
        self._frames_t: list[float] = []
        self._frames_q: list[np.ndarray] = []
        self._frames_sk: list[np.ndarray] = []
        self.decide_s: list[float] = []
        self.frame_to_decision_s = 0.0
        if predictor is not None:
            predictor.reset()
        self._emit_abs(t0, "trial_started", {"method": method, "seed": self.seed})
        self.supervisor.begin(t0)
        self.supervisor.set_goal(self.task.current.goal, not_before=t0)

    def _choose_station(self, allowed: list[str]) -> str:
        """The drop station for the block in the gripper (``Settings.station_choice="forecast"``): of the
        stations the round allows, the one farthest from the person over the method's latest forecast (the
        proactive one, or the reactive method's held pose): the least, over the forecast's steps, of the
        distance from the station and its approach pose to the nearest joint less the step's margin. Ties
        (and no forecast yet) keep the round's order."""
        forecast = self.last_forecast
        if forecast is None:
            return allowed[0]
        joints = np.asarray(forecast.joints, dtype=np.float64)  # (K, J, 3)
        margins = np.asarray(forecast.margins, dtype=np.float64)  # (K,)

        def clearance(name: str) -> float:
            poses = self._stations[name] + self._approach_up  # (2, 3): the station and its approach pose
            d = np.linalg.norm(joints[:, :, None, :] - poses[None, None], axis=-1)  # (K, J, 2)
            return float((d.min(axis=(1, 2)) - margins).min())

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
        c0 = time.perf_counter()
        frame = self.source.poll(t)
        if frame is None:
            return None
        self._check_intrusion(t, frame)
        # the body as the geometry sees it: the hand capsules out to the fingertips (the predictor keeps the
        # tracked joints it was trained on)
        body = dataclasses.replace(frame, joints=reach_fingertips(frame.joints))
        if self.method == "proactive":
            forecast = self.predictor.update(frame)
            if self.anticipation is not None:
                forecast = self.anticipation.apply(frame, forecast)
            forecast = dataclasses.replace(forecast, joints=reach_fingertips(forecast.joints))
            if self.options.plan_margin_m > 0:
                extra = self.options.plan_margin_m
                forecast = dataclasses.replace(forecast, margins=forecast.margins + extra)
        else:
            margin = self.options.tracking_margin_m + self.options.plan_margin_m
            forecast = HumanForecast.hold(body, margin_m=margin)
        tracked, frame = frame, body
        decision = self.supervisor.on_frame(frame, forecast, t_now=t)
        self.decide_s.append(decision.decide_s)
        self.frame_to_decision_s = time.perf_counter() - c0  # validation + prediction + decision
        self.last_decision = decision
        sep = decision.separation_m + self.config.tracking_margin_m
        self.min_separation_m = min(self.min_separation_m, sep)
        self.last_forecast = forecast
        self.last_frame = frame
        self._recent.append(frame)
        if self.options.record_frames:
            self._frames_t.append(self.elapsed(t))
            self._frames_q.append(np.asarray(self.last_state.q, dtype=np.float32))
            self._frames_sk.append(np.asarray(tracked.joints, dtype=np.float32))
        return decision

    def _check_intrusion(self, t: float, frame: HumanFrame) -> None:
        """A person who moved faster than a person can since the last frame appeared (or the tracker jumped
        to someone else): a protective stop, and the predictor starts over."""
        prev = self._last_tracked
        self._last_tracked = frame
        if prev is None or not frame.t > prev.t:
            return
        speeds = np.linalg.norm(frame.joints - prev.joints, axis=1) / (frame.t - prev.t)
        speed = float(speeds.max())
        if not is_intrusion(speeds, body_mps=self.options.intrusion_speed_mps):
            return
        self.intrusions += 1
        log.warning("intrusion: the person moved at %.1f m/s between two frames; protective stop", speed)
        self._emit_abs(t, "intrusion", {"speed_mps": speed})
        self.supervisor.intrusion(t)
        self._recent.clear()
        if self.predictor is not None:
            self.predictor.reset()

    def _judge(self, t: float, state: RobotState) -> None:
        """The ground-truth monitor's check of this servo tick."""
        mon = self.monitor
        assert mon is not None
        if self.truth is not None:
            joints = reach_fingertips(np.asarray(self.truth(t), dtype=np.float64))
            prev = self._truth_prev
            before, dt = (joints, 0.0) if prev is None else (prev[1], t - prev[0])
            self._truth_prev = (t, joints)
        else:  # no truth (a real cell): the tracker's frames are the best there is
            frame = self.last_frame
            if frame is None:
                return
            old = self._older_frame(frame)
            joints = frame.joints
            before, dt = (joints, 0.0) if old is None else (old.joints, frame.t - old.t)
        violations, contacts, harmful_before = mon.violations, mon.contacts, mon.harmful_contacts
        sample = mon.check(t, state.q, state.qd, joints, before, dt)
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
        if not self.supervisor.estopped:  # after an E-stop nothing is commanded until reset
            try:
                self.robot.servo(cmd.q, cmd.qd, t)
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
        while self._releases and self._releases[0][0] <= t:
            _, station = self._releases.pop(0)
            self.completed_tasks += 1
            self._emit_abs(t, "task_completed", {"station": station, "index": self.completed_tasks})
            self.source.notify_block_placed(station, t)
        if self.elapsed(t) >= self.duration_s - 1e-9:
            self.finish(t, "completed", "duration")

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
        n = min(len(self._frames_t), len(self._frames_q), len(self._frames_sk))
        if n <= start:
            return None
        return TrialFrames(
            t=np.asarray(self._frames_t[start:n], dtype=np.float64),
            q=np.stack(self._frames_q[start:n]),
            skeleton=np.stack(self._frames_sk[start:n]),
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


def make_validated_source(source: Any, cell: WorkCell, *, stale_timeout_s: float = 0.35) -> ValidatedSource:
    """``source`` behind the cell's frame checks and a stale watchdog (``Settings.stale_timeout_s``; a
    :class:`ValidatedSource` is returned as it is)."""
    if isinstance(source, ValidatedSource):
        return source
    watchdog = StaleWatchdog(stale_timeout_s)
    return ValidatedSource(source, validator=FrameValidator.for_workcell(cell), watchdog=watchdog)


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
