"""A fake UR controller that speaks RTDE (the server side), run in its own process, for the RTDE tests.

Protocol (Universal Robots' RTDE guide, protocol version 2): TCP port 30004; every package is a header
``>HB`` (size including the header, type) and a payload. Types handled: ``V`` request protocol version,
``v`` get URControl version, ``O`` set up outputs (frequency + variable names -> recipe id + types),
``I`` set up inputs (names -> recipe id + types), ``S`` start, ``P`` pause, ``U`` data package (outputs
from the controller at the set-up frequency; inputs from the client).

It is enough for ``rtde_receive.RTDEReceiveInterface`` (ur_rtde) to connect and read ``timestamp``,
``actual_q``, ``actual_qd``, ``robot_mode``, ``safety_mode``... . The controller's "arm" follows servo
set-points that arrive as RTDE *inputs* (``input_int_register_0`` = command, ``input_double_register_0..5``
= q), which is what :class:`FakeControl` sends: a stand-in for ``RTDEControlInterface``, whose real
implementation also needs the dashboard server and a URScript interpreter on the controller.

Each fake binds its own loopback address (127.x.y.z), because ur_rtde always uses port 30004.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import os
import queue
import select
import socket
import struct
import threading
import time
from typing import Any

RTDE_PORT = 30004

OUTPUT_TYPES = {
    "timestamp": "DOUBLE",
    "target_q": "VECTOR6D",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "runtime_state": "UINT32",
    "speed_scaling": "DOUBLE",
    "target_speed_fraction": "DOUBLE",
}
PACK = {
    "DOUBLE": ">d",
    "VECTOR6D": ">6d",
    "INT32": ">i",
    "UINT32": ">I",
    "UINT8": ">B",
    "VECTOR6INT32": ">6i",
}

CMD_NONE, CMD_SERVOJ, CMD_SERVO_STOP, CMD_STOP_SCRIPT = 0, 1, 2, 3

# Shared state (doubles): actual q (6), servo packages, stop packages, script stops, clients, data sent,
# last servo q (6), max servo step (rad), protective stop flag.
A_Q, A_SERVOS, A_STOPS, A_SCRIPT_STOPS, A_CLIENTS, A_SENT, A_LAST, A_MAX_STEP, A_PSTOP = (
    0,
    6,
    7,
    8,
    9,
    10,
    11,
    17,
    18,
)
A_LEN = 19

_addresses = itertools.count(1)


def free_loopback_address() -> str:
    """A loopback address (127.a.b.c) that no other fake of this or another test process uses."""
    n = next(_addresses)
    return f"127.{20 + os.getpid() % 200}.{(os.getpid() // 200) % 250 + 1}.{n % 250 + 1}"


def _pkg(kind: str, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", 3 + len(payload), ord(kind)) + payload


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise ConnectionError("closed")
        buf += chunk
    return bytes(buf)


class _Controller:
    """Shared controller state, served to every connection (threads of the fake's process)."""

    def __init__(self, state: Any, q0: list[float]) -> None:
        self.state = state
        self.lock = threading.Lock()
        self.t = 0.0
        self.q = list(q0)
        self.qd = [0.0] * 6
        self.silent = False
        self.pstop = False
        with state.get_lock():
            state[A_Q : A_Q + 6] = self.q

    def outputs(self, names: list[str]) -> bytes:
        with self.lock:
            values = {
                "timestamp": self.t,
                "target_q": self.q,
                "actual_q": self.q,
                "actual_qd": self.qd,
                "robot_mode": 7,  # RUNNING
                "safety_mode": 3 if self.pstop else 1,  # PROTECTIVE_STOP / NORMAL
                "runtime_state": 2,  # PLAYING
                "speed_scaling": 1.0,
                "target_speed_fraction": 1.0,
            }
        out = b""
        for n in names:
            fmt = PACK[OUTPUT_TYPES[n]]
            v = values[n]
            out += struct.pack(fmt, *v) if isinstance(v, list) else struct.pack(fmt, v)
        return out

    def tick(self, dt: float) -> None:
        with self.lock:
            self.t += dt

    def servo(self, command: int, q: list[float], dt: float) -> None:
        st = self.state
        with self.lock, st.get_lock():
            if command == CMD_SERVOJ and not self.pstop:
                step = max(abs(a - b) for a, b in zip(q, self.q, strict=True))
                st[A_MAX_STEP] = max(st[A_MAX_STEP], step)
                self.qd = [(a - b) / dt for a, b in zip(q, self.q, strict=True)]
                self.q = list(q)
                st[A_SERVOS] += 1
                st[A_LAST : A_LAST + 6] = q
            elif command == CMD_SERVO_STOP:
                self.qd = [0.0] * 6
                st[A_STOPS] += 1
            elif command == CMD_STOP_SCRIPT:
                self.qd = [0.0] * 6
                st[A_SCRIPT_STOPS] += 1
            st[A_Q : A_Q + 6] = self.q


def _serve_client(conn: socket.socket, ctrl: _Controller, stop: threading.Event) -> None:
    out_names: list[str] = []
    in_types: list[str] = []
    freq, started, next_send = 125.0, False, 0.0
    with ctrl.state.get_lock():
        ctrl.state[A_CLIENTS] += 1
    try:
        while not stop.is_set():
            timeout = max(0.0, next_send - time.monotonic()) if started else 0.05
            readable, _, _ = select.select([conn], [], [], min(timeout, 0.05))
            if readable:
                size, kind = struct.unpack(">HB", _recv_exact(conn, 3))
                body = _recv_exact(conn, size - 3)
                kind_c = chr(kind)
                if kind_c == "V":
                    conn.sendall(_pkg("V", b"\x01"))
                elif kind_c == "v":
                    conn.sendall(_pkg("v", struct.pack(">IIII", 5, 12, 0, 0)))
                elif kind_c == "O":
                    freq = struct.unpack(">d", body[:8])[0]
                    out_names = [n for n in body[8:].decode().split(",") if n]
                    types = [OUTPUT_TYPES.get(n, "NOT_FOUND") for n in out_names]
                    out_names = [n for n in out_names if n in OUTPUT_TYPES]
                    conn.sendall(_pkg("O", b"\x01" + ",".join(types).encode()))
                elif kind_c == "I":
                    names = [n for n in body.decode().split(",") if n]
                    in_types = ["INT32" if n.startswith("input_int_register_") else "DOUBLE" for n in names]
                    conn.sendall(_pkg("I", b"\x02" + ",".join(in_types).encode()))
                elif kind_c == "S":
                    started, next_send = True, time.monotonic()
                    conn.sendall(_pkg("S", b"\x01"))
                elif kind_c == "P":
                    started = False
                    conn.sendall(_pkg("P", b"\x01"))
                elif kind_c == "U" and in_types:
                    command = struct.unpack(">i", body[1:5])[0]
                    q = list(struct.unpack(">6d", body[5:53]))
                    ctrl.servo(command, q, 1.0 / freq)
            now = time.monotonic()
            if started and out_names and now >= next_send:
                next_send += 1.0 / freq
                if next_send < now:
                    next_send = now + 1.0 / freq
                ctrl.tick(1.0 / freq)
                if not ctrl.silent:
                    conn.sendall(_pkg("U", b"\x01" + ctrl.outputs(out_names)))
                    with ctrl.state.get_lock():
                        ctrl.state[A_SENT] += 1
    except (ConnectionError, OSError, struct.error):
        pass
    finally:
        conn.close()
        with ctrl.state.get_lock():
            ctrl.state[A_CLIENTS] -= 1


def serve(host: str, q0: list[float], commands: Any, state: Any, ready: Any) -> None:
    """The fake controller process: accept RTDE clients on ``host:30004`` until told to stop."""
    ctrl = _Controller(state, q0)
    stop = threading.Event()
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((host, RTDE_PORT))
    srv.listen(8)
    srv.settimeout(0.05)
    ready.set()
    threads: list[threading.Thread] = []
    try:
        while True:
            try:
                cmd = commands.get_nowait()
            except queue.Empty:
                cmd = None
            if cmd is not None:
                kind = cmd[0]
                if kind == "stop":
                    break
                with ctrl.lock:
                    if kind == "set_q":
                        ctrl.q = list(cmd[1])
                    elif kind == "silent":
                        ctrl.silent = bool(cmd[1])
                    elif kind == "pstop":
                        ctrl.pstop = bool(cmd[1])
                    with state.get_lock():
                        if kind == "reset_max_step":
                            state[A_MAX_STEP] = 0.0
                        state[A_Q : A_Q + 6] = ctrl.q
                        state[A_PSTOP] = 1.0 if ctrl.pstop else 0.0
            try:
                conn, _ = srv.accept()
            except TimeoutError:
                continue
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            th = threading.Thread(target=_serve_client, args=(conn, ctrl, stop), daemon=True)
            th.start()
            threads.append(th)
    finally:
        stop.set()
        srv.close()
        for th in threads:
            th.join(1.0)


class FakeController:
    """Test-side handle of a fake controller process (a context manager)."""

    def __init__(self, q0: list[float], *, host: str | None = None) -> None:
        self.host = host or free_loopback_address()
        ctx = mp.get_context("spawn")
        self.commands = ctx.Queue(maxsize=16)
        self.state = ctx.Array("d", A_LEN, lock=True)
        self.ready = ctx.Event()
        self.proc = ctx.Process(
            target=serve, args=(self.host, list(q0), self.commands, self.state, self.ready), daemon=True
        )

    def __enter__(self) -> FakeController:
        self.proc.start()
        if not self.ready.wait(20.0):
            self.close()
            raise RuntimeError(f"the fake RTDE controller did not start on {self.host}")
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.commands.put(("stop",), timeout=1.0)
        self.proc.join(5.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(2.0)

    def send(self, *cmd: object) -> None:
        self.commands.put(cmd, timeout=1.0)

    def value(self, index: int, n: int = 1) -> Any:
        with self.state.get_lock():
            return list(self.state[index : index + n]) if n > 1 else self.state[index]


class FakeControl:
    """A stand-in for ``rtde_control.RTDEControlInterface``: sends ``servoJ`` set-points to the fake
    controller as RTDE inputs (command in ``input_int_register_0``, q in ``input_double_register_0..5``)."""

    def __init__(self, host: str, frequency: float) -> None:
        self.sock = socket.create_connection((host, RTDE_PORT), timeout=2.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock.sendall(_pkg("V", struct.pack(">H", 2)))
        self._expect("V")
        names = ["input_int_register_0"] + [f"input_double_register_{i}" for i in range(6)]
        self.sock.sendall(_pkg("I", ",".join(names).encode()))
        self.recipe = self._expect("I")[0]
        self.sock.sendall(_pkg("S"))
        self._expect("S")
        self.connected = True
        self.servo_calls = 0

    def _expect(self, kind: str) -> bytes:
        while True:
            size, k = struct.unpack(">HB", _recv_exact(self.sock, 3))
            body = _recv_exact(self.sock, size - 3)
            if chr(k) == kind:
                return body

    def _send(self, command: int, q: list[float]) -> bool:
        try:
            self.sock.sendall(_pkg("U", bytes([self.recipe]) + struct.pack(">i6d", command, *q)))
            return True
        except OSError:
            self.connected = False
            return False

    def servoJ(
        self, q: list[float], speed: float, acceleration: float, t: float, lookahead: float, gain: float
    ) -> bool:
        self.servo_calls += 1
        return self._send(CMD_SERVOJ, list(q))

    def servoStop(self, a: float = 10.0) -> bool:
        return self._send(CMD_SERVO_STOP, [0.0] * 6)

    def stopScript(self) -> None:
        self._send(CMD_STOP_SCRIPT, [0.0] * 6)

    def isConnected(self) -> bool:
        return self.connected

    def disconnect(self) -> None:
        self.connected = False
        self.sock.close()


def fake_control_factory(host: str, rate_hz: float) -> FakeControl:
    """``control_factory`` for :class:`~app.cell.rtde.backend.RtdeRobot` (runs in the worker process)."""
    return FakeControl(host, rate_hz)


class BlockingReceive:
    """A receive interface without a network that answers a few reads, then blocks (a hung ur_rtde call)."""

    def __init__(self, host: str, frequency: float, variables: list[str]) -> None:
        self.calls = 0
        self.t = 0.0

    def getTimestamp(self) -> float:
        self.calls += 1
        if self.calls > 50:
            time.sleep(3600.0)  # hangs like a blocked C++ call
        self.t += 0.008
        return self.t

    def getActualQ(self) -> list[float]:
        return [0.1, -1.5, 1.5, -1.5, -1.5, 0.0]

    def getActualQd(self) -> list[float]:
        return [0.0] * 6

    def getSafetyMode(self) -> int:
        return 1

    def getRobotMode(self) -> int:
        return 7

    def disconnect(self) -> None:
        pass


def blocking_receive_factory(host: str, rate_hz: float, variables: list[str]) -> BlockingReceive:
    return BlockingReceive(host, rate_hz, variables)
