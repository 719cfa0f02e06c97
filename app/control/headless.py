"""Headless trials: the runtime's engine on the simulated clock, single-threaded and deterministic.

One loop advances a :class:`~app.cell.clock.SimClock` in servo ticks; a frame is read at every camera
period. Backup plans run lazily (:class:`~app.control.backup.InlinePlanJobs`): a plan is computed when the
switch that its own frame's decision scheduled is due, and its *measured* compute time decides, as in live
mode, whether it met the deadline ``D`` (the decisions are the same as with eager computation; see there).
The emergency plan's measured compute time delays its start likewise. A run is therefore deterministic for a
seed apart from those measured times (pass ``fixed_compute_s`` to fix them too, e.g. in tests).

The trial's world is the live runtime's assembly (:func:`app.control.world.build_trial_world`) with a
simulated robot.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from app.cell.clock import SimClock
from app.cell.source import HumanSource
from app.config import Settings, WorkCell
from app.control.backup import InlinePlanJobs
from app.control.engine import EngineOptions, TrialEngine
from app.control.metrics import Method
from app.control.results import TrialResult
from app.control.stack import PlanningStack
from app.control.world import build_trial_world
from app.prediction.forecast import Predictor

if TYPE_CHECKING:
    from app.cell.tracker import TrackerModel

log = logging.getLogger(__name__)

#: ``observer(t, engine)`` is called after every servo tick (tests use it for independent checks).
Observer = Callable[[float, TrialEngine], None]


def run_headless_trial(
    *,
    settings: Settings,
    cell: WorkCell | None = None,
    method: Method,
    duration_s: float,
    seed: int,
    participant_seed: int | None = None,
    source: Literal["sim", "replay"] = "sim",
    clip: str | Path | None = None,
    servo_rate_hz: float = 125.0,
    options: EngineOptions | None = None,
    stack: PlanningStack | None = None,
    predictor: Predictor | None = None,
    human: HumanSource | None = None,
    fixed_compute_s: float | None = None,
    observer: Observer | None = None,
    robot_factory: Callable[[SimClock, np.ndarray], Any] | None = None,
    forecast: Literal["model", "oracle"] = "model",
    tracker: TrackerModel | None = None,
) -> TrialResult:
    """Run one trial on the simulated clock and return its metrics, events and frames.

    Args:
        settings: D, F, planner workers (and ``replay_clip`` for ``source="replay"``).
        cell: The work cell (default: the one of ``settings``).
        method: ``proactive`` or ``reactive``.
        duration_s: Simulated length of the trial (s).
        seed: The trial's seed (operator behaviour and noise, assembly order).
        participant_seed: The participant's seed (body, habits, assembly order); default ``seed``.
        source: ``sim`` (simulated operator) or ``replay`` (a recorded clip, looped).
        clip: Clip for ``replay`` (default ``settings.replay_clip``).
        servo_rate_hz: Robot command rate (Hz).
        options: Engine options (monitor, frame recording, dwell times).
        stack: The planning stack (default: built for ``cell``, cached per process).
        predictor: The proactive predictor (default: the shipped one).
        human: A ready human source instead of ``source`` (tests).
        fixed_compute_s: Charge this compute time for every backup plan instead of the measured one.
        observer: Called as ``observer(t, engine)`` after each servo tick.
        robot_factory: ``(clock, q0) -> RobotBackend`` instead of a :class:`SimRobot` (tests).
        forecast: The proactive method's forecast: ``model`` (the motion predictor) or ``oracle`` (the
            simulated operator's own future, :class:`~app.cell.operator_sim.OracleForecaster`: the bound
            of what proactive planning can gain; ``source="sim"`` only).
        tracker: The tracker between the true person and the runtime (default: the settings', by
            :meth:`~app.cell.tracker.TrackerModel.from_settings`). Not applied to a ``human`` given by the
            caller, whose frames the runtime sees as they are.

    The true person (the simulated operator without noise, or the clip) is what the ground-truth monitor
    judges the robot against; the runtime sees them only through the tracker model.
    """
    from app.cell.robot import RobotConnectionError, SimRobot

    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    if not servo_rate_hz > 0:
        raise ValueError(f"servo_rate_hz must be > 0, got {servo_rate_hz}")
    clock = SimClock(0.0)
    world = build_trial_world(
        settings,
        cell if cell is not None else settings.load_workcell(),
        seed=seed,
        participant_seed=participant_seed,
        source=source,
        clip=clip,
        human=human,
        tracker=tracker,
        method=method,
        forecast=forecast,
        predictor=predictor,
        stack=stack,
        make_robot=lambda q0: SimRobot(clock, q0=q0) if robot_factory is None else robot_factory(clock, q0),
        options=options,
        servo_rate_hz=servo_rate_hz,
    )
    robot = world.robot
    wall0 = time.perf_counter()
    engine = world.engine(
        method=method,
        duration_s=duration_s,
        t0=0.0,
        jobs_factory=lambda computer, _cfg: InlinePlanJobs(computer, fixed_compute_s=fixed_compute_s),
    )
    dt = 1.0 / servo_rate_hz
    n_ticks = round(duration_s * servo_rate_hz)
    try:
        for k in range(n_ticks + 1):
            t = k * dt
            clock.set(t)
            engine.frame_tick(t)  # a frame is processed at the first tick after it arrived
            engine.servo_tick(t)
            if observer is not None:
                observer(t, engine)
            if not engine.running:
                break
        if engine.running:
            engine.finish(clock.now(), "completed", "duration")
    finally:
        try:
            robot.stop()
            robot.close()
        except RobotConnectionError as exc:
            log.warning("robot could not be stopped at the end of the trial: %s", exc)
    return world.result(engine, wall_s=time.perf_counter() - wall0)
