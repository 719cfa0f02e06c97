"""The parent side of the RTDE connection: :class:`RtdeRobot`, a :class:`~app.cell.robot.RobotBackend`.

It starts the worker process (:mod:`app.cell.rtde.worker`) and talks to it through shared memory (latest
state, latest servo set-point: newest wins, nothing queues up) and two bounded queues (commands in, events
out), detects a hung worker by its heartbeat, and raises :class:`~app.cell.robot.RobotConnectionError` with
a message that says what to check.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import queue
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np

from app.cell.clock import Clock, WallClock
from app.cell.joint_tracking import JointLimits, ServoCommand
from app.cell.robot import RobotConnectionError, RobotState, _check_scale
from app.cell.rtde.worker import (
    FAULT_LEN,
    S_CONNECTED,
    S_CONNECTS,
    S_HEARTBEAT,
    S_PSTOP,
    S_Q,
    S_QD,
    S_ROBOT_PSTOP,
    S_SAFETY,
    S_SCALE,
    S_T,
    SAFETY_MODE_NAMES,
    SERVO_LEN,
    STATE_LEN,
    WorkerConfig,
    default_control_factory,
    default_receive_factory,
    worker_main,
)

__all__ = ["RtdeRobot"]

log = logging.getLogger(__name__)


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
        probe: Run :func:`~app.cell.rtde.wire.probe_rtde` before the ur_rtde constructors (recommended).
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
