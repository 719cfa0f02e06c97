"""What a trial produces and shows: :class:`TrialFrames` (its frames at the camera rate),
:class:`TrialResult` (its metrics, events, frames and the judge's verdict) and :class:`Snapshot` (the live
state the operator's screens draw)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from app.cell.bodies import frame_bodies, recorded_bodies
from app.control.metrics import TrialEvent, TrialMetrics
from app.prediction.skeleton import body_count
from app.safety.modes import PartMode, binding_part, mode_text, region_text
from app.safety.monitor import MonitorTotals

__all__ = ["ShownSpeed", "Snapshot", "TrialFrames", "TrialResult", "TrialStatus", "robot_mode"]

TrialStatus = Literal["completed", "aborted"]


@dataclass(frozen=True, slots=True)
class TrialFrames:
    """A trial's frames at the camera rate (the study database's recorded frames).

    Attributes:
        t: (T,) seconds since the trial started.
        q: (T, 6) robot joint positions (rad).
        skeleton: (T, B, J, 3) every tracked body's joints in the world frame (m), NaN in the body slots a
            frame does not use (the layout of :mod:`app.cell.bodies`), or None when none were recorded.
            A single-body array (T, J, 3) is taken as one slot, id 0.
        body_ids: (T, B) the tracker's id of each body slot, -1 where unused (None: the single-body
            layout, ids 0; filled in on construction).
    """

    t: np.ndarray
    q: np.ndarray
    skeleton: np.ndarray | None
    body_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.skeleton is not None:
            sk, ids = recorded_bodies(self.skeleton, self.body_ids)
            if sk.shape[0] != self.t.shape[0]:
                raise ValueError(
                    f"TrialFrames skeleton must have {self.t.shape[0]} frames, got {sk.shape[0]}"
                )
            object.__setattr__(self, "skeleton", sk)
            object.__setattr__(self, "body_ids", ids)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def bodies(self, i: int) -> tuple[np.ndarray, tuple[int, ...]]:
        """Frame ``i``'s bodies: joints stacked (B_i*J, 3) and their ids (none without a skeleton)."""
        if self.skeleton is None or self.body_ids is None:
            return np.zeros((0, 3)), ()
        return frame_bodies(self.skeleton, self.body_ids, i)


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
            "plan_choices": {
                "forecast": m.plans_forecast,
                "reactive": m.plans_reactive,
                "reactive_only": m.plans_reactive_only,
                "reactive_gain_s": m.reactive_gain_s,
            },
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
        skeleton: (B*J, 3) the latest pose of every tracked body, stacked as in
            :class:`~app.prediction.skeleton.HumanFrame` (m, world), or None (no frame yet; a frame with
            nobody in view has B = 0).
        body_ids: The tracker's id of each body of ``skeleton`` (B,) (filled in as 0, 1, ... where not given).
        forecast: (H, B*J, 3) the latest forecast of every body, stacked alike, or None.
        forecast_body_ids: The id of each body of ``forecast`` (filled in as for ``body_ids``).
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
        speed_shown: The speed scale the operator's screens print (:class:`ShownSpeed`); None: print
            ``speed_scale``.
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
    speed_shown: float | None = None
    body_ids: tuple[int, ...] = ()
    forecast_body_ids: tuple[int, ...] = ()

    @property
    def limiting_part(self) -> int:
        """Index of the part that limits the robot (:func:`app.safety.modes.binding_part`; -1: none)."""
        return binding_part(self.part_modes)

    @property
    def mode(self) -> str | None:
        """The robot's mode: the limiting part's (:attr:`app.safety.modes.PartMode.label`), ``stopped``
        under an E-stop, None without a trial. The one field the operator page and the 3D view show."""
        return robot_mode(self.part_modes, estopped=self.estopped)

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
        for name, ids_name in (("skeleton", "body_ids"), ("forecast", "forecast_body_ids")):
            v = getattr(self, name)
            ids = tuple(int(i) for i in getattr(self, ids_name))
            if v is not None:
                n = body_count(v.shape[-2]) if v.ndim >= 2 else -1
                if not ids:
                    ids = tuple(range(n))
                if len(ids) != n:
                    raise ValueError(f"Snapshot {ids_name} {ids} do not match {name} of shape {v.shape}")
            object.__setattr__(self, ids_name, ids)
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
            "speed_shown": float(self.speed_scale if self.speed_shown is None else self.speed_shown),
            "separation_m": num(self.separation_m),
            "required_separation_m": num(self.required_separation_m),
            "planning_ms": [round(float(x), 3) for x in self.planning_ms],
            "counters": {k: (num(v) if isinstance(v, float) else v) for k, v in self.counters.items()},
            "q": arr(self.q, 5),
            "p_world_tcp": arr(self.p_world_tcp),
            "skeleton": arr(self.skeleton),
            "body_ids": list(self.body_ids),
            "forecast": arr(self.forecast),
            "forecast_body_ids": list(self.forecast_body_ids),
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


class ShownSpeed:
    """The speed the operator's screens print, one number for the page and the 3D view alike.

    Each draws the newest snapshot at its own rate (the page at its animation frames, the 3D view's texts
    when they change), so a number that changes with every snapshot would differ between the two for as long
    as one lags. The shown speed is the snapshot's own where the state or the mode changed, else it is
    refreshed on a grid of ``rate_hz`` of the snapshot clock and held in between: both screens print it from
    whichever snapshot they draw and change it within a frame of each other.
    """

    def __init__(self, rate_hz: float = 4.0) -> None:
        if not rate_hz > 0:
            raise ValueError(f"ShownSpeed.rate_hz must be > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self._held: tuple[Any, int, float] | None = None

    def __call__(self, t: float, key: Any, speed: float) -> float:
        """The speed to print for the snapshot at ``t`` (s) with the state and mode ``key`` and the speed
        scale ``speed``."""
        slot = math.floor(float(t) * self.rate_hz)
        if self._held is None or self._held[0] != key or self._held[1] != slot:
            self._held = (key, slot, float(speed))
        return self._held[2]


def robot_mode(part_modes: tuple[PartMode, ...], *, estopped: bool) -> str | None:
    """The robot's mode (:attr:`Snapshot.mode`): its limiting part's label, ``stopped`` under an E-stop,
    None without parts (no trial)."""
    if estopped:
        return "stopped"
    k = binding_part(part_modes)
    return None if k < 0 else part_modes[k].label
