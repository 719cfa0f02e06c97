"""The RTDE worker process (:func:`worker_main`; why a process: :mod:`app.cell.rtde`).

It connects (:func:`~app.cell.rtde.wire.probe_rtde`, then ``RTDEReceiveInterface`` and
``RTDEControlInterface``), then runs a fixed-rate loop at the controller's rate (500 Hz on e-Series): read
the state, run the watchdog, apply commands, shape the set-point with the shared
:class:`~app.cell.joint_tracking.JointTracker` (limits, speed scale, stop ramps) and send ``servoJ``. No new
state within ``watchdog_s`` means the connection is lost: the arm is stopped, the error reported, the
software protective stop latched, and it reconnects up to ``reconnect_attempts`` times. Every exit path
(close, loss, SIGTERM, parent death, exception) goes through ``servoStop`` / ``stopScript`` /
``disconnect`` in a ``finally``.

The parent (:class:`~app.cell.rtde.backend.RtdeRobot`) reads and writes the shared memory laid out here
(``S_*``: the latest state; ``V_*``: the latest servo set-point) and the two bounded queues (commands in,
events out). Times are ``time.monotonic``.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import queue
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.cell.clock import RateLoop, WallClock
from app.cell.joint_tracking import JointLimits, JointTracker, ServoCommand, warm_up_compiled
from app.cell.robot import RobotConnectionError
from app.cell.rtde.wire import probe_rtde

__all__ = ["WorkerConfig", "worker_main"]

log = logging.getLogger(__name__)

#: What the worker reads from the controller.
RECEIVE_VARIABLES: tuple[str, ...] = (
    "timestamp",
    "actual_q",
    "actual_qd",
    "robot_mode",
    "safety_mode",
    "runtime_state",
    "speed_scaling",
)
#: Safety modes in which the arm may move (UR: 1 NORMAL, 2 REDUCED).
SAFE_MODES = (1, 2)
SAFETY_MODE_NAMES = {
    1: "NORMAL",
    2: "REDUCED",
    3: "PROTECTIVE_STOP",
    4: "RECOVERY",
    5: "SAFEGUARD_STOP",
    6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP",
    8: "VIOLATION",
    9: "FAULT",
    10: "VALIDATE_JOINT_ID",
    11: "UNDEFINED_SAFETY_MODE",
    12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}

# Shared state layout (doubles).
S_HEARTBEAT, S_PHASE, S_T, S_Q, S_QD = 0, 1, 2, 3, 9
S_PSTOP, S_ROBOT_PSTOP, S_SCALE, S_CONNECTED, S_SAFETY, S_ROBOT_MODE, S_ROBOT_TS = 15, 16, 17, 18, 19, 20, 21
S_IGNORED, S_CONNECTS = 22, 23
STATE_LEN = 24
# Servo slot layout (doubles): sequence number, time, q, qd.
V_SEQ, V_T, V_Q, V_QD = 0, 1, 2, 8
SERVO_LEN = 14
#: Bytes of the shared fault message.
FAULT_LEN = 1024

PHASE_STARTING, PHASE_CONNECTED, PHASE_LOST, PHASE_FAILED, PHASE_CLOSED = 0.0, 1.0, 2.0, 3.0, 4.0


def default_receive_factory(host: str, rate_hz: float, variables: list[str]) -> Any:
    """``rtde_receive.RTDEReceiveInterface(host, rate_hz, variables)`` (ur_rtde)."""
    import rtde_receive

    return rtde_receive.RTDEReceiveInterface(host, rate_hz, variables)


def default_control_factory(host: str, rate_hz: float) -> Any:
    """``rtde_control.RTDEControlInterface(host, rate_hz)`` (ur_rtde; uploads its control script)."""
    import rtde_control

    return rtde_control.RTDEControlInterface(host, rate_hz)


@dataclass(frozen=True)
class WorkerConfig:
    """Everything the worker needs (picklable; factories must be module-level callables).

    Attributes:
        host: Robot address.
        rate_hz: Control rate (Hz): 500 for e-Series, 125 for CB3.
        watchdog_s: No new controller timestamp within this time means the connection is lost.
        probe_timeout_s: Timeout of each step of :func:`probe_rtde`.
        probe: Run :func:`probe_rtde` before constructing the ur_rtde interfaces.
        reconnect_attempts: Reconnections after a loss before giving up (0: never reconnect).
        reconnect_backoff_s: Wait between reconnection attempts.
        limits: Joint limits as plain lists (see :meth:`JointLimits.as_lists`).
        lookahead_s: ``servoJ`` lookahead time (0.03..0.2 s).
        gain: ``servoJ`` proportional gain (100..2000).
        stop_decel_rad_s2: Deceleration passed to ``servoStop``.
        receive_factory: ``(host, rate_hz, variables) -> RTDEReceiveInterface``-like.
        control_factory: ``(host, rate_hz) -> RTDEControlInterface``-like, or ``None`` for a read-only
            connection (state only; servo commands raise in the parent).
    """

    host: str
    rate_hz: float = 500.0
    watchdog_s: float = 0.1
    probe_timeout_s: float = 1.0
    probe: bool = True
    reconnect_attempts: int = 2
    reconnect_backoff_s: float = 1.0
    limits: dict[str, list[float]] = field(default_factory=dict)
    lookahead_s: float = 0.1
    gain: float = 300.0
    stop_decel_rad_s2: float = 4.0
    receive_factory: Callable[[str, float, list[str]], Any] = default_receive_factory
    control_factory: Callable[[str, float], Any] | None = default_control_factory


class _CloseRequestedError(Exception):
    """Raised inside the worker when the parent asked it to close (or died)."""


class _LostError(Exception):
    """Raised inside the worker when the connection is lost."""


class _Worker:
    def __init__(self, cfg: WorkerConfig, cmd_q: Any, evt_q: Any, state: Any, servo: Any, fault: Any) -> None:
        self.cfg = cfg
        self.fault = fault
        self.cmd_q = cmd_q
        self.evt_q = evt_q
        self.state = state
        self.servo = servo
        self.clock = WallClock()
        self.limits = JointLimits(**{k: np.asarray(v) for k, v in cfg.limits.items()})
        self.receive: Any = None
        self.control: Any = None
        self.pstop = False
        self.scale = 1.0
        self.connects = 0
        self.ignored = 0

    # -- plumbing ---------------------------------------------------------------------------------------
    def emit(self, kind: str, message: str = "") -> None:
        # The fault text goes to shared memory first, so a parent that sees the phase change also sees why.
        if kind in ("lost", "failed"):
            _write_text(self.fault, message)
        elif kind in ("connected", "reconnected"):
            _write_text(self.fault, "")
        with contextlib.suppress(queue.Full):
            self.evt_q.put_nowait({"kind": kind, "message": message, "t": self.clock.now()})

    def set_phase(self, phase: float, *, connected: bool) -> None:
        with self.state.get_lock():
            self.state[S_PHASE] = phase
            self.state[S_CONNECTED] = 1.0 if connected else 0.0
            self.state[S_HEARTBEAT] = self.clock.now()

    def parent_alive(self) -> bool:
        parent = mp.parent_process()
        return parent is None or parent.is_alive()

    def drain_commands(self, tracker: JointTracker | None) -> str | None:
        """Apply queued commands; returns 'stop' if the tracker must ramp down."""
        action = None
        while True:
            try:
                cmd = self.cmd_q.get_nowait()
            except queue.Empty:
                return action
            kind = cmd[0]
            if kind == "close":
                raise _CloseRequestedError
            if kind == "speed_scale":
                self.scale = float(cmd[1])
            elif kind == "stop":
                action = "stop"
            elif kind == "protective_stop":
                self.pstop = True
                action = "stop"
            elif kind == "reset_protective_stop":
                self.pstop = False
                self.ignored = 0
                action = "stop"

    def wait_interruptible(self, seconds: float) -> None:
        end = self.clock.now() + seconds
        while self.clock.now() < end:
            self.drain_commands(None)
            if not self.parent_alive():
                raise _CloseRequestedError
            time.sleep(0.02)

    # -- connection -------------------------------------------------------------------------------------
    def open(self) -> None:
        cfg = self.cfg
        if cfg.probe:
            version = probe_rtde(cfg.host, timeout_s=cfg.probe_timeout_s)
            log.info("RTDE controller %s at %s", ".".join(map(str, version)), cfg.host)
        try:
            self.receive = cfg.receive_factory(cfg.host, cfg.rate_hz, list(RECEIVE_VARIABLES))
        except Exception as exc:  # ur_rtde raises RuntimeError and friends
            raise RobotConnectionError(f"RTDE receive interface to {cfg.host} failed: {exc}") from exc
        if cfg.control_factory is not None:
            try:
                self.control = cfg.control_factory(cfg.host, cfg.rate_hz)
            except Exception as exc:
                raise RobotConnectionError(
                    f"RTDE control interface to {cfg.host} failed: {exc}; the robot must be in remote "
                    "control mode with no other program holding the RTDE inputs"
                ) from exc

    def shutdown(self, *, moving: bool) -> None:
        """Stop the arm and disconnect; never raises."""
        control, receive = self.control, self.receive
        self.control = self.receive = None
        if control is not None:
            if moving:
                with contextlib.suppress(Exception):
                    control.servoStop(self.cfg.stop_decel_rad_s2)
            with contextlib.suppress(Exception):
                control.stopScript()
            with contextlib.suppress(Exception):
                control.disconnect()
        if receive is not None:
            with contextlib.suppress(Exception):
                receive.disconnect()

    # -- main loop --------------------------------------------------------------------------------------
    def read(self) -> tuple[float, np.ndarray, np.ndarray, int, int]:
        r = self.receive
        return (
            float(r.getTimestamp()),
            np.asarray(r.getActualQ(), dtype=float),
            np.asarray(r.getActualQd(), dtype=float),
            int(r.getSafetyMode()),
            int(r.getRobotMode()),
        )

    def first_state(self) -> tuple[float, np.ndarray, np.ndarray, int, int]:
        """Wait for the first data package after connecting (ur_rtde returns before it arrives)."""
        cfg = self.cfg
        deadline = self.clock.now() + max(1.0, 5.0 * cfg.watchdog_s)
        while True:
            ts, q, qd, safety, robot_mode = self.read()
            if ts > 0.0 and q.shape == (6,) and np.all(np.isfinite(q)):
                break
            if self.clock.now() > deadline:
                raise RobotConnectionError(
                    f"the controller at {cfg.host} accepted the RTDE set-up but sent no state "
                    f"(joint positions) within {max(1.0, 5.0 * cfg.watchdog_s):.1f} s"
                )
            time.sleep(0.002)
        with self.state.get_lock():
            st = self.state
            st[S_HEARTBEAT] = st[S_T] = self.clock.now()
            st[S_Q : S_Q + 6] = q.tolist()
            st[S_QD : S_QD + 6] = qd.tolist()
            st[S_SCALE] = self.scale
            st[S_PSTOP] = 1.0 if self.pstop else 0.0
            st[S_ROBOT_PSTOP] = 0.0 if safety in SAFE_MODES else 1.0
            st[S_SAFETY], st[S_ROBOT_MODE], st[S_ROBOT_TS] = safety, robot_mode, ts
        return ts, q, qd, safety, robot_mode

    def run_connected(self, first: tuple[float, np.ndarray, np.ndarray, int, int]) -> None:
        cfg = self.cfg
        ts, q, qd, safety, robot_mode = first
        tracker = JointTracker(q, self.limits, max_substep_s=1.0 / cfg.rate_hz)
        loop = RateLoop(self.clock, cfg.rate_hz)
        dt = loop.period_s
        last_ts, last_change = ts, self.clock.now()
        servo_seq = self.servo[V_SEQ]
        active = False  # a set-point stream is being sent with servoJ
        stopping = False
        tick = 0
        while True:
            now = self.clock.now()
            ts, q, qd, safety, robot_mode = self.read()
            if ts != last_ts:
                last_ts, last_change = ts, now
            elif now - last_change > cfg.watchdog_s:
                raise _LostError(
                    f"no state from the robot at {cfg.host} for {now - last_change:.3f} s "
                    f"(watchdog {cfg.watchdog_s:.3f} s): connection lost, arm stopped"
                )
            if self.control is not None and not self.control.isConnected():
                raise _LostError(f"the RTDE control connection to {cfg.host} dropped: arm stopped")
            if self.drain_commands(tracker) == "stop":
                tracker.set_command(None)
                stopping = active
            robot_stopped = safety not in SAFE_MODES
            with self.servo.get_lock():
                seq = self.servo[V_SEQ]
                raw = list(self.servo[V_T : V_QD + 6]) if seq != servo_seq else None
            if raw is not None:
                servo_seq = seq
                if self.pstop or robot_stopped or self.control is None:
                    self.ignored += 1
                else:
                    if not active:  # start the set-point stream from where the arm is
                        tracker.q, tracker.qd = q.copy(), np.zeros(6)
                    tracker.set_command(ServoCommand(raw[0], np.array(raw[1:7]), np.array(raw[7:13])))
                    active, stopping = True, False
            if robot_stopped and active:
                tracker.set_command(None)
                active = stopping = False
            if active:
                tracker.step(now, dt, speed_scale=self.scale, stopping=stopping)
                if stopping and tracker.at_rest:
                    self.control.servoStop(cfg.stop_decel_rad_s2)
                    active = stopping = False
                else:
                    self.control.servoJ(tracker.q.tolist(), 0.0, 0.0, dt, cfg.lookahead_s, cfg.gain)
            with self.state.get_lock():
                st = self.state
                st[S_HEARTBEAT] = now
                st[S_T] = last_change
                st[S_Q : S_Q + 6] = q.tolist()
                st[S_QD : S_QD + 6] = qd.tolist()
                st[S_PSTOP] = 1.0 if self.pstop else 0.0
                st[S_ROBOT_PSTOP] = 1.0 if robot_stopped else 0.0
                st[S_SCALE] = self.scale
                st[S_SAFETY] = safety
                st[S_ROBOT_MODE] = robot_mode
                st[S_ROBOT_TS] = ts
                st[S_IGNORED] = self.ignored
            tick += 1
            if tick % 50 == 0 and not self.parent_alive():
                raise _CloseRequestedError
            loop.sleep()

    def main(self) -> None:
        cfg = self.cfg
        attempts_left = cfg.reconnect_attempts
        warm_up_compiled(self.limits)  # before any connection: the control loop's first step must not stall
        try:
            while True:
                try:
                    self.open()
                    first = self.first_state()
                except RobotConnectionError as exc:
                    self.shutdown(moving=False)
                    if self.connects == 0 or attempts_left <= 0:
                        self.emit("failed", str(exc))
                        self.set_phase(PHASE_FAILED, connected=False)
                        return
                    attempts_left -= 1
                    self.emit("reconnecting", f"{exc}; {attempts_left} attempt(s) left")
                    self.wait_interruptible(cfg.reconnect_backoff_s)
                    continue
                self.connects += 1
                attempts_left = cfg.reconnect_attempts
                with self.state.get_lock():
                    self.state[S_CONNECTS] = self.connects
                self.set_phase(PHASE_CONNECTED, connected=True)
                self.emit("connected" if self.connects == 1 else "reconnected", cfg.host)
                try:
                    self.run_connected(first)
                except _LostError as exc:
                    # Stop first, report, then latch the protective stop: after a reconnection the arm does
                    # not jump to a stale set-point; the supervisor must reset it.
                    self.emit("lost", str(exc))
                    self.set_phase(PHASE_LOST, connected=False)
                    self.pstop = True
                    self.shutdown(moving=True)
                    if attempts_left <= 0:
                        note = f"not reconnecting (reconnect_attempts={cfg.reconnect_attempts})"
                        self.emit("failed", f"{exc}; {note}")
                        self.set_phase(PHASE_FAILED, connected=False)
                        return
                    self.wait_interruptible(cfg.reconnect_backoff_s)
        except _CloseRequestedError:
            pass
        finally:
            self.shutdown(moving=True)
            self.set_phase(PHASE_CLOSED, connected=False)
            self.emit("closed", "")


def _raise_exit(signum: int, frame: object) -> None:
    raise _CloseRequestedError


def _write_text(buf: Any, text: str) -> None:
    data = text.encode("utf-8", "replace")[: len(buf) - 1]
    with buf.get_lock():
        buf.value = data


def worker_main(cfg: WorkerConfig, cmd_q: Any, evt_q: Any, state: Any, servo: Any, fault: Any) -> None:
    """Entry point of the RTDE worker process (see the module docstring)."""
    signal.signal(signal.SIGTERM, _raise_exit)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the parent, which closes us cleanly
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s rtde-worker %(levelname)s %(message)s")
    worker = _Worker(cfg, cmd_q, evt_q, state, servo, fault)
    try:
        worker.main()
    except _CloseRequestedError:
        pass
    except Exception as exc:  # report anything unexpected before the process ends
        worker.emit("failed", f"RTDE worker crashed: {type(exc).__name__}: {exc}")
        raise
