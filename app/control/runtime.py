"""The live runtime: the cell's engine on background threads and the wall clock, for the operator app.

Threads (started by :meth:`Runtime.start`, joined with timeouts by :meth:`Runtime.stop`, none at import or
construction):

- *frame* thread, at the camera rate (:class:`~app.cell.clock.RateLoop`): reads the human source, runs
  validation -> predictor -> supervisor decision, publishes a :class:`Snapshot` to the subscribers;
- *servo* thread, at the robot rate: advances the supervisor (path time, speed governor, switches) and
  commands the robot;
- *planner* pool (per trial): the backup plans, at most ``ceil(D / F)`` in flight
  (:class:`~app.control.backup.PoolPlanJobs`);
- *notifier* thread: calls the trial and event listeners (e.g. the study database) off the control threads,
  through a bounded queue.

Without a running trial the robot holds where it is and the frames still flow (the viewers see the person).
``robot.stop()`` runs in a ``finally`` of the servo thread and of :meth:`Runtime.stop`.

A trial's world (person, tracker, validation, predictor, planning stack, robot) is assembled by
:func:`app.control.world.build_trial_world`, as for headless trials on the simulated clock:
:func:`run_headless_trial` (re-exported from :mod:`app.control.headless`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from app.cell.clock import Clock, RateLoop, WallClock
from app.cell.robot import RobotBackend, RobotConnectionError
from app.cell.source import HumanSource
from app.cell.validation import REJECT_REASONS, ValidatedSource
from app.config import Settings, WorkCell
from app.control.backup import ForegroundGate, PoolPlanJobs
from app.control.engine import EngineOptions, TrialEngine
from app.control.headless import run_headless_trial
from app.control.metrics import METHODS, Method, TrialEvent, TrialMetrics
from app.control.results import ShownSpeed, Snapshot, TrialFrames, TrialResult, robot_mode
from app.control.stack import PlanningStack
from app.control.world import PredictorInfo, TrialWorld, build_trial_world, predictor_info
from app.planning.collision import ROBOT_LINKS
from app.prediction.forecast import HumanForecast, Predictor

log = logging.getLogger(__name__)

__all__ = [
    "IngestUnavailable",
    "Runtime",
    "RuntimeNotReady",
    "Snapshot",
    "Subscription",
    "TrialAlreadyRunning",
    "TrialCheckpoint",
    "TrialFrames",
    "TrialResult",
    "run_headless_trial",
]

TrialListener = Callable[[int, TrialMetrics, list[TrialEvent], str], None]


@dataclass(frozen=True, slots=True)
class TrialCheckpoint:
    """What a running trial has so far, for a checkpoint in the study database.

    Attributes:
        trial_id: The running trial.
        elapsed_s: Trial time of the checkpoint (s since the trial started).
        metrics: The trial's metrics so far (``duration_s`` is ``elapsed_s``, about).
        frames: The recorded frames from index ``first_frame`` on, or None (none recorded since).
        first_frame: Index of the first frame in ``frames`` among all the trial's recorded frames.
    """

    trial_id: int
    elapsed_s: float
    metrics: TrialMetrics
    frames: TrialFrames | None
    first_frame: int


EventListener = Callable[[int | None, TrialEvent], None]


class TrialAlreadyRunning(RuntimeError):  # noqa: N818 (the contract's name)
    """A trial was started while another one runs; stop it first (``stop_trial``)."""


class RuntimeNotReady(RuntimeError):  # noqa: N818 (like the API's names)
    """The runtime cannot start a trial now (not started, E-stop latched, robot lost); the message says
    why."""


class IngestUnavailable(RuntimeError):  # noqa: N818 (the API's name)
    """Frames were pushed but the runtime does not read a stream (set ``HRC_HUMAN_SOURCE=stream``)."""


# --------------------------------------------------------------------------------------------------------
# Snapshot subscriptions
# --------------------------------------------------------------------------------------------------------


class Subscription:
    """A bounded queue of snapshots for one viewer; when full, the oldest snapshot is dropped.

    Args:
        maxsize: Most snapshots kept.
        on_close: Called once when the subscription closes.
    """

    def __init__(self, maxsize: int = 8, *, on_close: Callable[[Subscription], None] | None = None) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self._items: deque[Snapshot] = deque(maxlen=maxsize)
        self._cond = threading.Condition()
        self._closed = False
        self._on_close = on_close
        self.dropped = 0

    def put(self, snapshot: Snapshot) -> None:
        with self._cond:
            if self._closed:
                return
            if len(self._items) == self._items.maxlen:
                self.dropped += 1
            self._items.append(snapshot)
            self._cond.notify()

    def get(self, timeout: float | None = 1.0) -> Snapshot | None:
        """The oldest waiting snapshot, waiting at most ``timeout`` s (None: 1 s); None on timeout/close."""
        wait_s = 1.0 if timeout is None else max(float(timeout), 0.0)
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(wait_s)
            if self._items:
                return self._items.popleft()
            return None

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._items.clear()
            self._cond.notify_all()
        if self._on_close is not None:
            self._on_close(self)


# --------------------------------------------------------------------------------------------------------
# The runtime
# --------------------------------------------------------------------------------------------------------


class _LockedSource(HumanSource):
    """A human source shared by the frame thread (``frame_at``) and the servo thread (``notify``).

    A source that validates its own frames (the stream source) stays one behind the lock: its frames are not
    validated twice, and its counters (every rejection of a pushed message) are the ones reported."""

    def __init__(self, source: HumanSource) -> None:
        self.source = source
        self._lock = threading.Lock()
        self.validates_frames = bool(source.validates_frames)
        self._truth = source.ground_truth()

    @property
    def counters(self) -> dict[str, int]:
        return dict(self.source.counters)  # type: ignore[attr-defined]  # a source that validates_frames

    def reset_counters(self) -> None:
        self.source.reset_counters()

    def frame_at(self, t: float) -> Any:
        with self._lock:
            return self.source.frame_at(t)

    def pose_at(self, t: float) -> np.ndarray:
        """The inner source's true pose at ``t`` (a simulated or recorded person's)."""
        assert self._truth is not None, "the inner source has no ground truth"
        with self._lock:
            return self._truth(t)

    def ground_truth(self) -> Callable[[float], np.ndarray] | None:
        return None if self._truth is None else self.pose_at

    def notify_block_placed(self, station: str, t: float) -> None:
        with self._lock:
            self.source.notify_block_placed(station, t)


@dataclass
class _LoopStats:
    """Timings of the live loops (bounded, newest kept), for benchmarks.

    Attributes:
        decide_ms: The supervisor's decision on each new frame (checks, separation; no backup search).
        frame_to_decision_ms: From the source handing over a new frame to the decision on it: validation,
            the people's tracks, prediction, decision.
        frame_ms: A whole frame tick, snapshot publication included.
        servo_late_ms: How late each servo tick woke up after its deadline.
        servo_overruns: Servo ticks that overran their period.
    """

    decide_ms: deque[float]
    frame_to_decision_ms: deque[float]
    frame_ms: deque[float]
    servo_late_ms: deque[float]
    servo_overruns: int = 0


class PlanningRecord(NamedTuple):
    """A live trial's planning so far.

    Attributes:
        times_s: The compute time (s) of every plan.
        deadline_misses: Its missed deadlines.
        waited_s: How long its plan jobs waited for the frames' decisions in all (s;
            :class:`~app.control.backup.ForegroundGate`), and ``waits`` how often.
    """

    times_s: list[float]
    deadline_misses: int
    waited_s: float
    waits: int


class Runtime:
    """The live cell: see the module docstring.

    Args:
        settings: Application settings (robot and human source, D, F, workers).
        cell: The work cell (default: ``settings.load_workcell()``).
        robot: A robot backend (default: :func:`app.cell.backends.make_robot` at :meth:`start`).
        source: A human source (default by ``settings.human_source``: a simulated participant of
            ``settings.population``, re-seeded for every trial; a replayed clip; or a
            :class:`~app.cell.human.StreamSource` fed by :meth:`ingest`).
        predictor: The proactive method's predictor (default: the shipped one, loaded at :meth:`start`).
        clock: The clock (default :class:`WallClock`).
        servo_rate_hz: Robot command rate (Hz).
        options: Engine options.
        stack: The planning stack (default: built for the cell at :meth:`start`).
    """

    def __init__(
        self,
        settings: Settings,
        *,
        cell: WorkCell | None = None,
        robot: RobotBackend | None = None,
        source: HumanSource | None = None,
        predictor: Predictor | None = None,
        clock: Clock | None = None,
        servo_rate_hz: float = 125.0,
        options: EngineOptions | None = None,
        stack: PlanningStack | None = None,
    ) -> None:
        if not servo_rate_hz > 0:
            raise ValueError(f"servo_rate_hz must be > 0, got {servo_rate_hz}")
        self.settings = settings
        self.cell = cell if cell is not None else settings.load_workcell()
        self.clock: Clock = clock if clock is not None else WallClock()
        self.servo_rate_hz = float(servo_rate_hz)
        self.options = options or EngineOptions(record_frames=False)
        self._robot = robot
        self._own_robot = robot is None
        self._source_given = source
        self._predictor = predictor
        self._stack = stack
        self._lock = threading.RLock()
        self._engine: TrialEngine | None = None
        self._trial_id: int | None = None
        self._gate: ForegroundGate | None = None  # the running trial's plan jobs' (PoolPlanJobs)
        self._world: TrialWorld | None = None
        self._source: ValidatedSource | None = None
        self._sim_source = False
        self._stream: Any | None = None
        self._threads: list[threading.Thread] = []
        self._stop = threading.Event()
        self._started = False
        self._estopped = False
        self._fault: str | None = None
        self._subs: list[Subscription] = []
        self._snapshot: Snapshot | None = None
        self._trial_listeners: list[TrialListener] = []
        self._event_listeners: list[EventListener] = []
        self._notify_q: queue.Queue[Callable[[], None] | None] = queue.Queue(maxsize=10000)
        self._tcp_cache: dict[int, np.ndarray] = {}
        self._last_frame: Any | None = None
        self._shown_speed = ShownSpeed()  # the one speed the page and the 3D view print
        self.last_result: TrialResult | None = None
        #: The proactive method's predictor as it runs (after :meth:`start`).
        self.predictor_info: PredictorInfo | None = None
        n = 4096
        self.stats = _LoopStats(deque(maxlen=n), deque(maxlen=n), deque(maxlen=n), deque(maxlen=16 * n))

    # -------------------------------------------------------------------------------------------- lifecycle
    @property
    def roadmap(self) -> Any | None:
        """The planner's roadmap (after :meth:`start`), for the 3D view."""
        return None if self._stack is None else self._stack.roadmap

    @property
    def robot(self) -> RobotBackend | None:
        return self._robot

    @property
    def world(self) -> TrialWorld | None:
        """The world of the current (or the next) trial (after :meth:`start`)."""
        return self._world

    def start(self) -> None:
        """Build what the cell needs (planning stack, robot, source, predictor) and start the threads.

        Raises:
            PredictorUnavailable: the predictor's weights cannot be used and ``HRC_HMP_FALLBACK`` is off.
        """
        with self._lock:
            if self._started:
                return
            self._open_world(seed=0)  # a predictor that cannot run stops the start before the robot is made
            self.predictor_info = predictor_info(self._predictor)
            if not _warm_up_compiled(
                self.settings, self.cell, self._stack, self._predictor, servo_rate_hz=self.servo_rate_hz
            ):
                _warm_up(self._predictor, self.cell)  # the trial of the first start ran this predictor
            self._stop.clear()
            self._started = True
            for name, target in (
                ("hrc-notifier", self._notify_loop),
                ("hrc-servo", self._servo_loop),
                ("hrc-frames", self._frame_loop),
            ):
                th = threading.Thread(target=target, name=name, daemon=True)
                th.start()
                self._threads.append(th)
        log.info(
            "runtime started (servo %.0f Hz, frames %.1f Hz)", self.servo_rate_hz, 1 / self._frame_period
        )

    def stop(self, *, timeout_s: float = 5.0) -> None:
        """End a running trial (aborted), stop the threads (joined with a timeout) and stop the robot."""
        with self._lock:
            if not self._started:
                return
            engine = self._engine
        try:
            if engine is not None and engine.running:
                engine.finish(self.clock.now(), "aborted", "shutdown")
                self._end_trial()
            self._stop.set()
            try:
                self._notify_q.put(None, timeout=timeout_s)
            except queue.Full:
                log.error("listener queue full at shutdown; pending notifications are dropped")
            for th in self._threads:
                th.join(timeout_s)
                if th.is_alive():
                    log.error("runtime thread %s did not stop within %.1f s", th.name, timeout_s)
            self._threads.clear()
        finally:
            robot = self._robot
            if robot is not None:
                try:
                    robot.stop()
                except Exception:
                    log.exception("robot.stop() failed while stopping the runtime")
                if self._own_robot:
                    try:
                        robot.close()
                    except Exception:
                        log.exception("robot.close() failed")
            for sub in list(self._subs):
                sub.close()
            with self._lock:
                self._started = False
        log.info("runtime stopped")

    def __enter__(self) -> Runtime:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def _frame_period(self) -> float:
        return float(self.settings.frame_period_s)

    def _open_world(self, *, seed: int) -> None:
        """(Re)build the trial's world (:func:`~app.control.world.build_trial_world`). The planning stack,
        the predictor, the robot and a source that is not simulated are made once; a simulated operator is
        re-seeded for every trial."""
        from app.cell.backends import make_robot

        clock, settings = self.clock, self.settings
        world = build_trial_world(
            settings,
            self.cell,
            seed=seed,
            t0=clock.now(),
            human=self._source_given,
            share=_LockedSource,
            predictor=self._predictor,
            require_weights=True,
            stack=self._stack,
            robot=self._robot,
            make_robot=lambda q0: make_robot(settings, clock, q0=q0),
            options=self.options,
            servo_rate_hz=self.servo_rate_hz,
        )
        self._world = world
        self._predictor, self._stack, self._robot = world.predictor, world.stack, world.robot
        self._source, self._stream = world.source, world.stream
        self._sim_source = self._source_given is None and settings.human_source == "sim"

    # -------------------------------------------------------------------------------------------- trials
    @property
    def running_trial_id(self) -> int | None:
        with self._lock:
            return self._trial_id if self._engine is not None and self._engine.running else None

    def planning_record(self) -> PlanningRecord:
        """The planning of the trial so far (empty before the first)."""
        with self._lock:
            engine, gate = self._engine, self._gate
        if engine is None or gate is None:
            return PlanningRecord([], 0, 0.0, 0)
        c = engine.supervisor.counters
        return PlanningRecord(list(c.planning_times_s), c.deadline_misses, gate.waited_s, gate.waits)

    def start_trial(self, *, trial_id: int, method: Method, duration_s: float, seed: int) -> None:
        """Start a trial now.

        Raises:
            TrialAlreadyRunning: another trial runs.
            RuntimeNotReady: the runtime is not started, the E-stop is latched or the robot is lost.
            ValueError: unknown method or a non-positive duration.
        """
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if not duration_s > 0:
            raise ValueError(f"duration_s must be > 0, got {duration_s}")
        with self._lock:
            if not self._started:
                raise RuntimeNotReady("the runtime is not started; call start() first")
            if self._engine is not None and self._engine.running:
                raise TrialAlreadyRunning(f"trial {self._trial_id} is running; stop it first")
            if self._estopped:
                raise RuntimeNotReady("the E-stop is latched; reset() first")
            if self._fault is not None:
                raise RuntimeNotReady(f"the robot is lost ({self._fault}); restart the runtime")
            if self._sim_source:
                self._open_world(seed=seed)
            elif self._source is not None:
                self._source.reset_counters()  # the trial counts its own frames and rejections
            assert self._world is not None
            clock = self.clock
            gate = self._gate = ForegroundGate()
            self._engine = self._world.engine(
                method=method,
                duration_s=duration_s,
                t0=clock.now(),
                jobs_factory=lambda computer, cfg: PoolPlanJobs(
                    computer, max_jobs=cfg.max_jobs, clock=clock, gate=gate
                ),
                on_event=lambda ev, tid=trial_id: self._post_event(tid, ev),
                seed=seed,
            )
            self._trial_id = trial_id
        log.info("trial %d started (%s, %.0f s, seed %d)", trial_id, method, duration_s, seed)

    def checkpoint(self, trial_id: int, *, first_frame: int = 0) -> TrialCheckpoint | None:
        """The running trial's metrics so far and its recorded frames from ``first_frame`` on; None when
        ``trial_id`` is not the running trial. Called by the trial recorder's thread (it reads the engine
        the frame and servo threads update, as the E-stop does): a read that races an update and fails is
        logged and answered None (the next checkpoint comes a moment later)."""
        with self._lock:
            engine = self._engine
            if engine is None or not engine.running or self._trial_id != trial_id:
                return None
        try:
            elapsed = engine.elapsed(self.clock.now())
            metrics = engine.metrics()
            frames = engine.frames(first_frame)
        except (RuntimeError, ValueError, IndexError) as exc:
            log.debug("trial %d: checkpoint skipped (%s)", trial_id, exc)
            return None
        return TrialCheckpoint(trial_id, float(elapsed), metrics, frames, int(first_frame))

    def stop_trial(self, reason: str = "operator") -> None:
        """End the running trial now (``aborted`` with ``reason``); no-op without one."""
        with self._lock:
            engine = self._engine
            if engine is None or not engine.running:
                return
            engine.finish(self.clock.now(), "aborted", reason)
        self._end_trial()

    def _end_trial(self) -> None:
        with self._lock:
            engine, trial_id, world = self._engine, self._trial_id, self._world
            if engine is None or engine.running or trial_id is None or world is None:
                return
            self._engine = None
            self._trial_id = None
        result = world.result(engine)
        self.last_result = result
        status, reason, metrics, events = result.status, result.reason, result.metrics, result.events
        if reason == "robot_fault":
            self._fault = "robot connection lost"
        log.info("trial %d ended: %s (%s), %d tasks", trial_id, status, reason, metrics.completed_tasks)
        for fn in list(self._trial_listeners):
            self._post(lambda fn=fn: fn(trial_id, metrics, events, status))

    def add_trial_listener(self, fn: TrialListener) -> None:
        """``fn(trial_id, metrics, events, status)`` after every trial (status ``completed``/``aborted``),
        called on the notifier thread."""
        self._trial_listeners.append(fn)

    def add_event_listener(self, fn: EventListener) -> None:
        """``fn(trial_id, event)`` for every event of a trial, on the notifier thread."""
        self._event_listeners.append(fn)

    def _post_event(self, trial_id: int, ev: TrialEvent) -> None:
        for fn in list(self._event_listeners):
            self._post(lambda fn=fn: fn(trial_id, ev))

    def _post(self, call: Callable[[], None]) -> None:
        try:
            self._notify_q.put(call, timeout=0.5)
        except queue.Full:
            log.error("listener queue full (%d); a notification was dropped", self._notify_q.maxsize)

    def _notify_loop(self) -> None:
        while True:
            try:
                call = self._notify_q.get(timeout=0.5)
            except queue.Empty:
                if self._stop.is_set():
                    return
                continue
            if call is None:
                return
            try:
                call()
            except Exception:
                log.exception("a trial/event listener raised")

    # -------------------------------------------------------------------------------------------- safety
    def estop(self, source: str = "api") -> None:
        """E-stop: the robot stops now (protective stop), a running trial ends (aborted); :meth:`reset` to
        go on."""
        t = self.clock.now()
        with self._lock:
            self._estopped = True
            engine = self._engine
        robot = self._robot
        if robot is not None:
            try:
                robot.protective_stop()
            except Exception:
                log.exception("protective stop failed; stopping the robot")
                robot.stop()
        if engine is not None and engine.running:
            engine.estop(t, source=source)
            engine.finish(t, "aborted", "estop")
            self._end_trial()
        self._publish(self._build_snapshot(self.clock.now()))
        log.warning("E-stop (%s)", source)

    def reset(self) -> None:
        """Clear the E-stop and the robot's protective stop.

        Raises:
            RuntimeError: the robot is lost (restart the runtime).
        """
        if self._fault is not None:
            raise RuntimeError(f"the robot is lost ({self._fault}); restart the runtime")
        robot = self._robot
        if robot is not None:
            robot.reset_protective_stop()
        with self._lock:
            self._estopped = False
        self._publish(self._build_snapshot(self.clock.now()))

    # -------------------------------------------------------------------------------------------- frames in
    def ingest(self, message: dict[str, Any] | str | bytes) -> None:
        """Push one tracker message (a dict, or its JSON text as received) to the stream source.

        Raises:
            IngestUnavailable: the runtime reads no stream.
            app.cell.validation.FrameRejected: the frame is invalid (the reason says why).
        """
        stream = self._stream
        if stream is None:
            raise IngestUnavailable(
                f"this runtime reads the {self.settings.human_source!r} source; set HRC_HUMAN_SOURCE=stream"
            )
        stream.push(message, self.clock.now())

    def frame_counts(self) -> dict[str, Any]:
        """The frames of the human source since the current trial started (before the first trial: since
        :meth:`start`) and the servo loop's overruns since :meth:`start`: ``frames_received``,
        ``frames_rejected`` ``{"total": n, "by_reason": {reason: n, ...}}`` (every reason of
        :data:`~app.cell.validation.REJECT_REASONS`, zeros included) and ``servo_overruns``."""
        source = self._source
        counters = dict(source.counters) if source is not None else {}
        by_reason = {r: int(counters.get(f"rejected_{r}", 0)) for r in REJECT_REASONS}
        rejected = int(counters.get("rejected", 0))
        return {
            "frames_received": int(counters.get("accepted", 0)) + rejected,
            "frames_rejected": {"total": rejected, "by_reason": by_reason},
            "servo_overruns": int(self.stats.servo_overruns),
        }

    # -------------------------------------------------------------------------------------------- loops
    def _frame_loop(self) -> None:
        loop = RateLoop(self.clock, 1.0 / self._frame_period)
        while not self._stop.is_set():
            t = self.clock.now()
            c0 = time.perf_counter()
            try:
                self._frame_tick(t)
            except Exception:
                log.exception("frame tick failed; the trial is aborted")
                with self._lock:
                    engine = self._engine
                if engine is not None and engine.running:
                    engine.finish(t, "aborted", "runtime_error")
                    self._end_trial()
            self.stats.frame_ms.append((time.perf_counter() - c0) * 1e3)
            loop.sleep()

    def _frame_tick(self, t: float) -> None:
        with self._lock:
            engine = self._engine
            source = self._source
        if engine is not None:
            decision = engine.frame_tick(t)
            if decision is not None:
                self.stats.decide_ms.append(decision.decide_s * 1e3)
                self.stats.frame_to_decision_ms.append(engine.frame_to_decision_s * 1e3)
                self._last_frame = engine.last_frame
            if not engine.running:
                self._end_trial()
        elif source is not None:
            frame = source.poll(t)
            if frame is not None:
                self._last_frame = frame
        self._publish(self._build_snapshot(t))

    def _servo_loop(self) -> None:
        loop = RateLoop(self.clock, self.servo_rate_hz)
        try:
            while not self._stop.is_set():
                with self._lock:
                    engine = self._engine
                if engine is not None and engine.running:
                    try:
                        engine.servo_tick(self.clock.now())
                    except RobotConnectionError as exc:
                        engine.finish(self.clock.now(), "aborted", "robot_fault")
                        self._fault = str(exc)
                    except Exception:
                        log.exception("servo tick failed; the trial is aborted and the robot stopped")
                        engine.finish(self.clock.now(), "aborted", "runtime_error")
                        if self._robot is not None:
                            self._robot.stop()
                deadline = loop.next_deadline
                if not loop.sleep():
                    self.stats.servo_overruns += 1
                self.stats.servo_late_ms.append(max(self.clock.now() - deadline, 0.0) * 1e3)
        finally:
            if self._robot is not None:
                try:
                    self._robot.stop()
                except Exception:
                    log.exception("robot.stop() failed at the end of the servo thread")

    # -------------------------------------------------------------------------------------------- snapshots
    def subscribe(self, maxsize: int = 8) -> Subscription:
        """A bounded queue of snapshots (oldest dropped when full); close it when done."""
        sub = Subscription(maxsize, on_close=self._unsubscribe)
        with self._lock:
            self._subs.append(sub)
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def _publish(self, snap: Snapshot) -> None:
        self._snapshot = snap
        with self._lock:
            subs = list(self._subs)
        for sub in subs:
            sub.put(snap)

    def snapshot(self) -> Snapshot:
        """The newest snapshot (built now when none was published yet)."""
        snap = self._snapshot
        return snap if snap is not None else self._build_snapshot(self.clock.now())

    def _tcp_path(self, traj: Any) -> np.ndarray | None:
        if traj is None or self._stack is None:
            return None
        key = id(traj)
        got = self._tcp_cache.get(key)
        if got is None:
            ts = np.linspace(
                traj.t_start, traj.t_end, max(2, min(60, int((traj.t_end - traj.t_start) * 20) + 2))
            )
            q = np.asarray(traj.q(ts)).reshape(-1, 6)
            got = self._stack.kin.fk_tcp(q)[:, :3, 3]
            if len(self._tcp_cache) > 8:
                self._tcp_cache.clear()
            self._tcp_cache[key] = got
        return got

    def _build_snapshot(self, t: float) -> Snapshot:
        with self._lock:
            engine = self._engine
            trial_id = self._trial_id
        robot = self._robot
        q = np.asarray(self.cell.robot.home_q, dtype=np.float64)
        if robot is not None:
            with contextlib.suppress(Exception):
                q = np.asarray(robot.state().q, dtype=np.float64)
        p_tcp = self._stack.kin.fk_tcp(q[None])[0, :3, 3] if self._stack is not None else np.zeros(3)
        frame = self._last_frame
        stale = self._source.is_stale(t) if self._source is not None else True
        base = dict(
            t=t,
            q=q,
            p_world_tcp=p_tcp,
            skeleton=None if frame is None else frame.joints,
            body_ids=() if frame is None else frame.body_ids,
            stale=stale,
            estopped=self._estopped,
        )
        if engine is None:
            state = "fault" if self._fault else ("estop" if self._estopped else "idle")
            return Snapshot(
                trial_id=None,
                state=state,
                method=None,
                speed_scale=0.0,
                separation_m=None,
                required_separation_m=None,
                planning_ms=(),
                counters={},
                **base,
            )
        st = engine.supervisor.status()
        fc = engine.last_forecast
        times = engine.supervisor.counters.planning_times_s[-20:]
        budget, by_goal = engine.time_budget()
        state = "estop" if self._estopped else st.state
        key = (state, robot_mode(st.modes, estopped=self._estopped))
        return Snapshot(
            trial_id=trial_id,
            state=state,
            method=engine.method,
            speed_scale=st.scale,
            separation_m=st.separation_m if math.isfinite(st.separation_m) else None,
            required_separation_m=st.required_separation_m,
            planning_ms=tuple(1e3 * x for x in times),
            counters=engine.counters(),
            forecast=None if fc is None else _shown_forecast(fc, self._frame_period),
            forecast_body_ids=() if fc is None else fc.body_ids,
            plan_tcp=self._tcp_path(st.plan),
            backup_tcp=self._tcp_path(st.backup),
            trial_elapsed_s=engine.elapsed(t),
            trial_duration_s=engine.duration_s,
            time_budget=budget,
            time_budget_by_goal=by_goal,
            part_modes=st.modes,
            part_names=ROBOT_LINKS if len(st.modes) == len(ROBOT_LINKS) else (),
            speed_shown=self._shown_speed(t, key, st.scale),
            **base,
        )


def _shown_forecast(fc: HumanForecast, period_s: float) -> np.ndarray:
    """The forecast's poses as a snapshot shows them: one per frame period over its horizon (K, J, 3),
    whatever its own samples (the arbitrated forecast's halfway samples add nothing to a picture, and would
    double the live messages)."""
    n = math.floor((fc.horizon_end - fc.t0) / period_s + 1e-6)
    return fc.poses_at(fc.t0 + period_s * np.arange(n + 1))[0]


_COMPILED_READY = False
_COMPILED_LOCK = threading.Lock()


def _warm_up_compiled(
    settings: Settings,
    cell: WorkCell,
    stack: Any,
    predictor: Predictor | None,
    *,
    servo_rate_hz: float = 125.0,
) -> bool:
    """Load the compiled inner loops (numba kernels of the speed governor, the simulated arm and operator,
    the planner's checks, the monitor and the forecast) before the runtime's threads start: a 2-s headless
    trial on the simulated cell, once per process.

    A kernel's first call in a process loads its machine code from the cache (about 0.1 s) or, on a fresh
    install, compiles it (seconds); in the servo loop that would be a stall of the robot's command stream.
    The warm-up drives a simulated arm only (never the configured robot) and keeps nothing of its trial.
    Returns whether its trial ran (False: an earlier start of this process ran it, or it failed).
    """
    global _COMPILED_READY
    with _COMPILED_LOCK:
        if _COMPILED_READY:
            return False
        t0 = time.perf_counter()
        ran = False
        try:
            run_headless_trial(
                settings=settings,
                cell=cell,
                method="proactive" if predictor is not None else "reactive",
                duration_s=2.0,
                seed=0,
                source="sim",
                stack=stack,
                predictor=predictor,
                servo_rate_hz=servo_rate_hz,
            )
            ran = True
        except Exception:
            log.exception("warm-up of the compiled loops failed; their first calls may stall the loops")
        finally:
            if predictor is not None:
                predictor.reset()
        _COMPILED_READY = True
        log.info("compiled control loops ready in %.1f s", time.perf_counter() - t0)
        return ran


def _warm_up(predictor: Predictor | None, cell: WorkCell) -> None:
    """Run the predictor on a few still frames (the first inference of a network is slow), then reset it."""
    if predictor is None:
        return
    from app.prediction.skeleton import NUM_JOINTS, HumanFrame

    op = cell.operator
    pose = np.tile([op.center_xy[0], op.center_xy[1], op.floor_z + 1.0], (NUM_JOINTS, 1))
    try:
        for k in range(12):
            predictor.update(HumanFrame(t=k / 30.0, joints=pose + 0.001 * k))
    except Exception:
        log.exception("predictor warm-up failed; the first frames may be slow")
    finally:
        predictor.reset()
