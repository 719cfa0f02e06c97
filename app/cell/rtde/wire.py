"""The RTDE wire as far as the app speaks it: package framing and :func:`probe_rtde`, a pure-Python
handshake (protocol version + controller version) with socket timeouts that tells "nothing listening",
"listening but silent" and "a UR controller" apart before ur_rtde is touched."""

from __future__ import annotations

import socket
import struct

from app.cell.robot import RobotConnectionError

__all__ = ["RTDE_PORT", "probe_rtde"]

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
