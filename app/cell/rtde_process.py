"""A real UR arm over RTDE (``ur_rtde``), driven from its own worker process.

Why a process: ``rtde_receive.RTDEReceiveInterface(...)`` and ``rtde_control.RTDEControlInterface(...)``
block inside their constructors *while holding the GIL* when a peer accepts the TCP connection but never
answers (measured with ur_rtde 1.6.5: every Python thread of the process freezes). In a separate
process such a hang costs nothing but that process, which the parent kills after its timeout.

Layers:

- :func:`probe_rtde`: a pure-Python RTDE handshake (protocol version + controller version) with socket
  timeouts: tells "nothing listening", "listening but silent" and "a UR controller" apart before ur_rtde
  is touched.
- :func:`worker_main`: the worker process. It connects (probe, then ``RTDEReceiveInterface`` and
  ``RTDEControlInterface``), then runs a fixed-rate loop at the controller's rate (500 Hz on e-Series):
  read the state, run the watchdog, apply commands, shape the set-point with the shared
  :class:`~app.cell.joint_tracking.JointTracker` (limits, speed scale, stop ramps) and send ``servoJ``.
  No new state within ``watchdog_s`` means the connection is lost: the arm is stopped, the error reported,
  the software protective stop latched, and it reconnects up to ``reconnect_attempts`` times. Every exit
  path (close, loss, SIGTERM, parent death, exception) goes through ``servoStop`` / ``stopScript`` /
  ``disconnect`` in a ``finally``.
- :class:`RtdeRobot`: the parent-side :class:`~app.cell.robot.RobotBackend`. It talks to the worker
  through shared memory (latest state, latest servo set-point: newest wins, nothing queues up) and two
  bounded queues (commands in, events out), detects a hung worker by its heartbeat, and raises
  :class:`~app.cell.robot.RobotConnectionError` with a message that says what to check.

Times in the worker are ``time.monotonic`` (system-wide, so comparable with
:class:`~app.cell.clock.WallClock`).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import queue
import signal
import socket
import struct
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from app.cell.clock import Clock, RateLoop, WallClock
from app.cell.joint_tracking import JointLimits, JointTracker, ServoCommand, warm_up_compiled
from app.cell.robot import RobotConnectionError, RobotState, _check_scale

__all__ = [
    "RTDE_PORT",
    "RtdeRobot",
    "WorkerConfig",
    "probe_rtde",
    "worker_main",
]

log = logging.getLogger(__name__)

#: The RTDE port of a UR controller (ur_rtde always uses it).
RTDE_PORT = 30004
RTDE_PROTOCOL_VERSION = 2
#: RTDE package types (UR's RTDE guide).
PKG_REQUEST_PROTOCOL_VERSION = ord("V")
PKG_GET_URCONTROL_VERSION = ord("v")
PKG_TEXT_MESSAGE = ord("M")
PKG_DATA = ord("U")
PKG_SETUP_OUTPUTS = ord("O")
PKG_SETUP_INPUTS = ord("I")
PKG_START = ord("S")
PKG_PAUSE = ord("P")

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


# ---------------------------------------------------------------------------------------------------------
# Wire helpers and the handshake probe
# ---------------------------------------------------------------------------------------------------------
def pack_package(package_type: int, payload: bytes = b"") -> bytes:
    """One RTDE package: header ``>HB`` (total size incl. the 3-byte header, type), then the payload."""
    return struct.pack(">HB", 3 + len(payload), package_type) + payload


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        buf += chunk
    return bytes(buf)


def read_package(sock: socket.socket) -> tuple[int, bytes]:
    """Read one RTDE package from ``sock`` (honours the socket's timeout); returns (type, payload)."""
    size, package_type = struct.unpack(">HB", _recv_exact(sock, 3))
    if size < 3:
        raise ConnectionError(f"malformed RTDE header (size {size})")
    return package_type, _recv_exact(sock, size - 3)


def probe_rtde(host: str, *, port: int = RTDE_PORT, timeout_s: float = 1.0) -> tuple[int, int, int, int]:
    """Check that a UR controller speaks RTDE at ``host:port``, within ``timeout_s`` per step.

    Connects, requests protocol version 2 and reads the controller version, then closes.

    Returns:
        The controller version (major, minor, bugfix, build).

    Raises:
        RobotConnectionError: nothing listens there, the peer is silent, or it is not an RTDE server.
    """
    where = f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except TimeoutError as exc:
        raise RobotConnectionError(
            f"no robot at {where}: the TCP connection timed out after {timeout_s:.1f} s; check the "
            "robot's IP address (HRC_ROBOT_HOST), that it is powered on and on the same network"
        ) from exc
    except OSError as exc:
        raise RobotConnectionError(
            f"no robot at {where}: {exc.strerror or exc}; check the robot's IP address (HRC_ROBOT_HOST) "
            "and that the controller is running (RTDE listens on port 30004)"
        ) from exc
    try:
        sock.settimeout(timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.sendall(pack_package(PKG_REQUEST_PROTOCOL_VERSION, struct.pack(">H", RTDE_PROTOCOL_VERSION)))
        _, payload = _read_reply(sock, PKG_REQUEST_PROTOCOL_VERSION)
        if not payload or payload[0] != 1:
            raise RobotConnectionError(f"the RTDE server at {where} refused protocol version 2")
        sock.sendall(pack_package(PKG_GET_URCONTROL_VERSION))
        _, payload = _read_reply(sock, PKG_GET_URCONTROL_VERSION)
        if len(payload) < 16:
            raise RobotConnectionError(f"malformed controller version from {where}")
        return struct.unpack(">IIII", payload[:16])
    except TimeoutError as exc:
        raise RobotConnectionError(
            f"the peer at {where} accepted the connection but did not answer the RTDE handshake within "
            f"{timeout_s:.1f} s; is this a UR controller, and is RTDE not blocked by another client?"
        ) from exc
    except (ConnectionError, OSError, struct.error) as exc:
        raise RobotConnectionError(f"RTDE handshake with {where} failed: {exc}") from exc
    finally:
        sock.close()


def _read_reply(sock: socket.socket, expected: int) -> tuple[int, bytes]:
    for _ in range(16):  # skip text messages the controller may interleave
        package_type, payload = read_package(sock)
        if package_type == expected:
            return package_type, payload
        if package_type != PKG_TEXT_MESSAGE:
            raise ConnectionError(f"unexpected RTDE package {chr(package_type)!r}, wanted {chr(expected)!r}")
    raise ConnectionError("too many RTDE text messages before the reply")


# ---------------------------------------------------------------------------------------------------------
# Worker process
# ---------------------------------------------------------------------------------------------------------
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


# ---------------------------------------------------------------------------------------------------------
# Parent side
# ---------------------------------------------------------------------------------------------------------
def _finalize(proc: Any, cmd_q: Any, timeout_s: float) -> None:
    if proc is None or not proc.is_alive():
        return
    with contextlib.suppress(Exception):
        cmd_q.put(("close",), timeout=0.1)
    proc.join(timeout_s)
    if proc.is_alive():
        proc.terminate()
        proc.join(1.0)
    if proc.is_alive():
        proc.kill()
        proc.join(1.0)


class RtdeRobot:
    """A UR arm over RTDE as a :class:`~app.cell.robot.RobotBackend`; the work runs in a worker process.

    Construction does nothing; :meth:`connect` (or ``with RtdeRobot(...) as robot:``) starts the worker and
    waits for the connection. The worker streams ``servoJ`` at ``rate_hz`` while a set-point is active:
    :meth:`servo` only publishes the newest set-point. :meth:`state` reports ``connected=False`` and a
    ``fault`` after a loss (the worker's watchdog) or when the worker stops answering (the heartbeat,
    ``hung_timeout_s``); :meth:`servo` then raises :class:`~app.cell.robot.RobotConnectionError`.

    Speed scale and protective stop are applied in the worker (the set-point is ramped within the
    acceleration limits; the software protective stop does not trigger the controller's own one). A
    protective stop reported by the controller (safety mode not NORMAL/REDUCED) shows as
    ``protective_stop=True`` with a ``fault`` naming the safety mode.

    Args:
        host: Robot address (RTDE on port 30004).
        clock: The runtime's clock; it must run at real-time rate (a :class:`WallClock`): servo times are
            converted to the worker's monotonic clock by a fixed offset.
        rate_hz: Control rate (Hz): 500 for e-Series, 125 for CB3.
        connect_timeout_s: How long :meth:`connect` waits for the worker to connect.
        watchdog_s: No new state within this time: connection lost.
        hung_timeout_s: No heartbeat from the worker within this time: worker killed, fault reported.
        probe: Run :func:`probe_rtde` before the ur_rtde constructors (recommended).
        reconnect_attempts: Automatic reconnections after a loss (the protective stop is latched).
        reconnect_backoff_s: Wait between reconnection attempts.
        limits: Joint limits (default UR5e).
        lookahead_s: ``servoJ`` lookahead time (s).
        gain: ``servoJ`` gain.
        receive_factory: Replaces ``RTDEReceiveInterface`` (tests, custom transports); module-level callable.
        control_factory: Replaces ``RTDEControlInterface``; ``None`` for a read-only connection.
    """

    def __init__(
        self,
        host: str,
        *,
        clock: Clock | None = None,
        rate_hz: float = 500.0,
        connect_timeout_s: float = 5.0,
        watchdog_s: float = 0.1,
        hung_timeout_s: float = 0.5,
        probe: bool = True,
        reconnect_attempts: int = 2,
        reconnect_backoff_s: float = 1.0,
        limits: JointLimits | None = None,
        lookahead_s: float = 0.1,
        gain: float = 300.0,
        receive_factory: Callable[[str, float, list[str]], Any] = default_receive_factory,
        control_factory: Callable[[str, float], Any] | None = default_control_factory,
    ) -> None:
        if not host:
            raise ValueError("RtdeRobot needs the robot's address (HRC_ROBOT_HOST)")
        self.host = host
        self.clock: Clock = clock if clock is not None else WallClock()
        self._wall = WallClock()
        self.connect_timeout_s = float(connect_timeout_s)
        self.hung_timeout_s = float(hung_timeout_s)
        lim = limits if limits is not None else JointLimits.ur5e()
        self._cfg = WorkerConfig(
            host=host,
            rate_hz=float(rate_hz),
            watchdog_s=float(watchdog_s),
            probe_timeout_s=min(1.0, float(connect_timeout_s)),
            probe=probe,
            reconnect_attempts=int(reconnect_attempts),
            reconnect_backoff_s=float(reconnect_backoff_s),
            limits=lim.as_lists(),
            lookahead_s=float(lookahead_s),
            gain=float(gain),
            receive_factory=receive_factory,
            control_factory=control_factory,
        )
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._cmd_q: Any = None
        self._evt_q: Any = None
        self._state: Any = None
        self._servo: Any = None
        self._finalizer: Any = None
        self._fault: str | None = None
        self._fault_text: Any = None
        self._events: list[dict[str, Any]] = []
        self._seq = 0

    # -- lifecycle --------------------------------------------------------------------------------------
    def connect(self, timeout_s: float | None = None) -> None:
        """Start the worker and wait (at most ``timeout_s``, default ``connect_timeout_s``) until connected.

        The wait blocks only the calling thread (it waits on a queue, without the GIL).

        Raises:
            RobotConnectionError: no robot at the address, a silent peer, ur_rtde failed, or the timeout
                passed (the worker is then killed).
        """
        if self._proc is not None and self._proc.is_alive():
            raise RuntimeError("RtdeRobot is already connected; close() it first or call reconnect()")
        timeout = self.connect_timeout_s if timeout_s is None else float(timeout_s)
        self._fault = None
        self._cmd_q = self._ctx.Queue(maxsize=64)
        self._evt_q = self._ctx.Queue(maxsize=64)
        self._state = self._ctx.Array("d", STATE_LEN, lock=True)
        self._fault_text = self._ctx.Array("c", FAULT_LEN, lock=True)
        self._servo = self._ctx.Array("d", SERVO_LEN, lock=True)
        self._proc = self._ctx.Process(
            target=worker_main,
            args=(self._cfg, self._cmd_q, self._evt_q, self._state, self._servo, self._fault_text),
            name=f"rtde-worker-{self.host}",
            daemon=True,
        )
        self._proc.start()
        self._finalizer = weakref.finalize(self, _finalize, self._proc, self._cmd_q, 3.0)
        deadline = self._wall.now() + timeout
        while True:
            remaining = deadline - self._wall.now()
            if remaining <= 0:
                self._kill_worker()
                raise RobotConnectionError(
                    f"no RTDE connection to {self.host} within {timeout:.1f} s: the peer accepted the TCP "
                    "connection but ur_rtde's set-up did not complete (a silent peer, or a controller that "
                    "is not ready); the worker process was killed. Check the address and remote control"
                )
            try:
                event = self._evt_q.get(timeout=min(remaining, 0.1))
            except queue.Empty:
                if not self._proc.is_alive():
                    self._drain_events()
                    raise RobotConnectionError(
                        self._fault or f"the RTDE worker for {self.host} exited during connection"
                    ) from None
                continue
            self._record(event)
            if event["kind"] == "connected":
                return
            if event["kind"] == "failed":
                self._proc.join(2.0)
                self._kill_worker()
                raise RobotConnectionError(event["message"])

    def reconnect(self, timeout_s: float | None = None) -> None:
        """Close the current worker (stopping the arm) and connect again."""
        self.close()
        self.connect(timeout_s)

    def close(self) -> None:
        """Stop the arm (servoStop, stopScript), disconnect, and end the worker; idempotent."""
        if self._proc is None:
            return
        if self._finalizer is not None:
            self._finalizer.detach()
        _finalize(self._proc, self._cmd_q, 3.0)
        self._drain_events()
        self._release()

    def _kill_worker(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(1.0)
        if self._finalizer is not None:
            self._finalizer.detach()
        self._release()

    def _release(self) -> None:
        for q in (self._cmd_q, self._evt_q):
            if q is not None:
                q.cancel_join_thread()
                q.close()
        self._cmd_q = self._evt_q = None
        self._proc = None

    def __enter__(self) -> RtdeRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- events -----------------------------------------------------------------------------------------
    def _record(self, event: dict[str, Any]) -> None:
        self._events.append(event)
        del self._events[:-100]
        kind = event["kind"]
        if kind in ("lost", "failed"):
            self._fault = event["message"]
            log.error("RTDE %s: %s", kind, event["message"])
        elif kind in ("connected", "reconnected"):
            self._fault = None
            log.info("RTDE %s: %s", kind, event["message"])
        elif kind == "reconnecting":
            log.warning("RTDE reconnecting: %s", event["message"])

    def _drain_events(self) -> None:
        if self._evt_q is None:
            return
        while True:
            try:
                self._record(self._evt_q.get_nowait())
            except (queue.Empty, OSError, ValueError):
                return

    def events(self) -> list[dict[str, Any]]:
        """Recent worker events; ``kind``: connected, lost, reconnecting, reconnected, failed, closed."""
        self._drain_events()
        return list(self._events)

    # -- RobotBackend -----------------------------------------------------------------------------------
    def _to_worker_time(self, t: float) -> float:
        return t + (self._wall.now() - self.clock.now())

    def _from_worker_time(self, t: float) -> float:
        return t + (self.clock.now() - self._wall.now())

    def state(self) -> RobotState:
        self._drain_events()
        if self._state is None:
            return RobotState(0.0, np.zeros(6), np.zeros(6), True, 1.0, False, fault="not connected")
        with self._state.get_lock():
            st = list(self._state)
        fault = self._fault or self._shared_fault()
        connected = st[S_CONNECTED] > 0.5
        alive = self._proc is not None and self._proc.is_alive()
        if connected and alive and self._wall.now() - st[S_HEARTBEAT] > self.hung_timeout_s:
            fault = (
                f"the RTDE worker for {self.host} stopped answering for more than "
                f"{self.hung_timeout_s:.2f} s (blocked inside ur_rtde?); it was killed, reconnect to continue"
            )
            self._fault = fault
            log.error(fault)
            self._kill_worker()
            connected = False
        elif connected and not alive:
            connected = False
            fault = fault or "the RTDE worker exited"
        robot_pstop = st[S_ROBOT_PSTOP] > 0.5
        if robot_pstop and connected:
            mode = int(st[S_SAFETY])
            fault = f"robot safety mode {SAFETY_MODE_NAMES.get(mode, mode)}"
        return RobotState(
            t=self._from_worker_time(st[S_T]) if st[S_T] else self.clock.now(),
            q=np.array(st[S_Q : S_Q + 6]),
            qd=np.array(st[S_QD : S_QD + 6]),
            protective_stop=st[S_PSTOP] > 0.5 or robot_pstop,
            speed_scale=st[S_SCALE] if connected else 0.0,
            connected=connected,
            fault=None if connected and not robot_pstop else (fault or "not connected"),
        )

    def _shared_fault(self) -> str | None:
        if self._fault_text is None:
            return None
        with self._fault_text.get_lock():
            text = self._fault_text.value.decode("utf-8", "replace")
        return text or None

    def _require_connected(self) -> None:
        if self._proc is None or self._state is None:
            raise RobotConnectionError(f"RtdeRobot({self.host!r}) is not connected; call connect() first")
        if self._state[S_CONNECTED] < 0.5 or not self._proc.is_alive():
            self._drain_events()
            raise RobotConnectionError(
                self._fault or self._shared_fault() or f"the connection to {self.host} is down"
            )

    def servo(self, q: np.ndarray, qd: np.ndarray, t: float) -> None:
        command = ServoCommand(float(t), q, qd)
        self._require_connected()
        if self._cfg.control_factory is None:
            raise RobotConnectionError("RtdeRobot was opened read-only (control_factory=None)")
        self._seq += 1
        t_worker = self._to_worker_time(command.t)
        values = [float(self._seq), t_worker, *command.q.tolist(), *command.qd.tolist()]
        with self._servo.get_lock():
            self._servo[:] = values

    def _command(self, *cmd: object) -> None:
        if self._cmd_q is None:
            return
        try:
            self._cmd_q.put(cmd, timeout=0.1)
        except queue.Full:
            raise RobotConnectionError(f"the RTDE worker for {self.host} is not taking commands") from None

    def stop(self) -> None:
        self._command("stop")

    def protective_stop(self) -> None:
        self._command("protective_stop")

    def reset_protective_stop(self) -> None:
        self._command("reset_protective_stop")

    def set_speed_scale(self, s: float) -> None:
        self._command("speed_scale", _check_scale(s))

    @property
    def worker_pid(self) -> int | None:
        """Process id of the worker (``None`` when not running)."""
        return None if self._proc is None else self._proc.pid

    @property
    def connections(self) -> int:
        """How many times the worker connected (1 + reconnections)."""
        return 0 if self._state is None else int(self._state[S_CONNECTS])

    def __repr__(self) -> str:
        return f"RtdeRobot(host={self.host!r}, rate_hz={self._cfg.rate_hz}, pid={self.worker_pid})"
