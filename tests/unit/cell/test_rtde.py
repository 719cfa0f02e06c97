"""RtdeRobot against a fake RTDE controller in another process.

What is covered, honestly:

- the receive path end to end with the real ``rtde_receive.RTDEReceiveInterface`` (ur_rtde) talking RTDE to
  the fake controller: the fake sends a known q, the backend reports it;
- the control path through the backend interface: ``RtdeRobot.servo`` -> worker process (set-point shaping
  within the limits, speed scale, protective stop, clean stop) -> a control transport -> the controller ->
  back through the real receive interface. The control transport is :class:`fake_rtde.FakeControl` (RTDE
  input registers), not ``rtde_control.RTDEControlInterface``, which needs a URScript interpreter and the
  dashboard server of a real controller or URSim;
- the pre-check, the watchdog (a controller that stops sending), reconnection, a hung worker, a silent peer
  (accepts the connection, never answers: the backend gives up and the test process keeps running), and no
  robot at the address.

The waits below poll with timeouts (a process on the other side); no assertion is about how long anything
took.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from fake_rtde import (
    A_CLIENTS,
    A_LAST,
    A_MAX_STEP,
    A_Q,
    A_SCRIPT_STOPS,
    A_SERVOS,
    A_STOPS,
    FakeController,
    blocking_receive_factory,
    fake_control_factory,
    free_loopback_address,
)

from app.cell.clock import WallClock
from app.cell.joint_tracking import JointLimits
from app.cell.robot import RobotBackend, RobotConnectionError
from app.cell.rtde.backend import RtdeRobot
from app.cell.rtde.wire import RTDE_PORT, probe_rtde

Q0 = [0.1, -1.4, 1.3, -1.5, -1.6, 0.2]
RATE_HZ = 125.0


def wait_for(pred: Callable[[], bool], timeout_s: float = 15.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture
def fake() -> Iterator[FakeController]:
    with FakeController(Q0) as ctrl:
        yield ctrl


def _robot(host: str, **kw: object) -> RtdeRobot:
    opts: dict[str, object] = {
        "rate_hz": RATE_HZ,
        "watchdog_s": 0.5,
        "hung_timeout_s": 5.0,
        "connect_timeout_s": 20.0,
        "reconnect_attempts": 0,
        "control_factory": None,
    }
    opts.update(kw)
    return RtdeRobot(host, clock=WallClock(), **opts)  # type: ignore[arg-type]


def _silent_listener() -> socket.socket:
    """A peer that accepts TCP connections (the kernel completes the handshake) and never answers."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind((free_loopback_address(), RTDE_PORT))
    srv.listen(8)
    return srv


def test_probe_reads_the_controller_version(fake: FakeController) -> None:
    assert probe_rtde(fake.host, timeout_s=5.0) == (5, 12, 0, 0)


def test_probe_no_robot_at_the_address() -> None:
    with pytest.raises(RobotConnectionError, match="no robot at"):
        probe_rtde(free_loopback_address(), timeout_s=1.0)  # nothing listens there: refused


def test_probe_silent_peer_times_out() -> None:
    srv = _silent_listener()
    try:
        with pytest.raises(RobotConnectionError, match="did not answer the RTDE handshake"):
            probe_rtde(srv.getsockname()[0], timeout_s=0.3)
    finally:
        srv.close()


def test_receive_round_trip_with_ur_rtde(fake: FakeController) -> None:
    robot = _robot(fake.host)
    assert isinstance(robot, RobotBackend)
    assert not robot.state().connected  # nothing happens before connect()
    robot.connect()
    try:
        st = robot.state()  # connect() returns once the first state has arrived
        assert st.connected
        np.testing.assert_allclose(st.q, Q0)
        np.testing.assert_allclose(st.qd, 0.0)
        assert not st.protective_stop and st.fault is None
        q1 = [0.3, -1.0, 1.0, -1.2, -1.5, 0.5]
        fake.send("set_q", q1)
        wait_for(lambda: np.allclose(robot.state().q, q1), what="the new q")
        # a read-only connection refuses servo commands with a clear error
        with pytest.raises(RobotConnectionError, match="read-only"):
            robot.servo(np.array(q1), np.zeros(6), 0.0)
        # the controller's own protective stop shows up in the state
        fake.send("pstop", True)
        wait_for(lambda: robot.state().protective_stop, what="protective stop")
        assert "PROTECTIVE_STOP" in (robot.state().fault or "")
    finally:
        robot.close()
    assert robot.worker_pid is None
    assert not robot.state().connected


def test_control_path_through_the_backend(fake: FakeController) -> None:
    limits = JointLimits.ur5e()
    robot = _robot(fake.host, control_factory=fake_control_factory)
    robot.connect()
    try:
        wait_for(lambda: robot.state().connected and robot.state().t > 0, what="first state")
        target = np.array(Q0) + np.array([0.4, -0.3, 0.2, 0.0, 0.1, -0.2])
        robot.servo(target, np.zeros(6), robot.clock.now())
        # the set-points stream to the controller, which moves; the receive path reports it back
        wait_for(lambda: np.allclose(robot.state().q, target, atol=1e-3), what="arrival at the target")
        np.testing.assert_allclose(fake.value(A_Q, 6), target, atol=1e-3)
        # the worker shaped the stream within the speed limit (one step per control period)
        assert fake.value(A_MAX_STEP) <= limits.qd_max.max() / RATE_HZ + 1e-9
        n_servos = fake.value(A_SERVOS)
        assert n_servos > 10
        # the set-point is held (and streamed) until stop(), which ends with servoStop
        robot.stop()
        wait_for(lambda: fake.value(A_STOPS) >= 1, what="servoStop after stop()")
        # speed scale: a new move with at most 25 % of the speed limit
        robot.set_speed_scale(0.25)
        fake.send("reset_max_step")
        wait_for(lambda: fake.value(A_MAX_STEP) == 0.0, what="max step reset")
        target2 = target + 0.3
        robot.servo(target2, np.zeros(6), robot.clock.now())
        wait_for(lambda: np.allclose(robot.state().q, target2, atol=1e-3), what="the second target")
        assert robot.state().speed_scale == 0.25
        step = fake.value(A_MAX_STEP)
        assert (
            0.5 * 0.25 * limits.qd_max.max() / RATE_HZ < step <= 0.25 * limits.qd_max.max() / RATE_HZ + 1e-9
        )
        # protective stop: ramps down, sends servoStop, ignores servo commands until reset
        stops = fake.value(A_STOPS)
        robot.servo(np.array(Q0), np.zeros(6), robot.clock.now())
        wait_for(lambda: not np.allclose(fake.value(A_LAST, 6), target2, atol=1e-2), what="motion")
        robot.protective_stop()
        wait_for(lambda: fake.value(A_STOPS) > stops, what="servoStop after protective_stop()")
        wait_for(lambda: robot.state().protective_stop, what="the protective stop flag")
        q_stopped = np.array(fake.value(A_Q, 6))
        servos = fake.value(A_SERVOS)
        robot.servo(target, np.zeros(6), robot.clock.now())
        time.sleep(0.3)
        assert fake.value(A_SERVOS) == servos  # ignored
        np.testing.assert_allclose(fake.value(A_Q, 6), q_stopped)
        robot.reset_protective_stop()
        wait_for(lambda: not robot.state().protective_stop, what="reset")
        robot.servo(target, np.zeros(6), robot.clock.now())
        wait_for(lambda: np.allclose(robot.state().q, target, atol=1e-3), what="motion after reset")
    finally:
        robot.close()
    # close() stopped the arm and the script on the controller, and the worker is gone
    wait_for(lambda: fake.value(A_SCRIPT_STOPS) >= 1, what="stopScript on close")
    wait_for(lambda: fake.value(A_CLIENTS) == 0, what="all connections closed")


def test_watchdog_reports_a_lost_connection_then_reconnects(fake: FakeController) -> None:
    robot = _robot(
        fake.host,
        control_factory=fake_control_factory,
        watchdog_s=0.3,
        # enough attempts to outlast the checks below on a loaded machine (each failed attempt takes about
        # watchdog + back-off); with 3 the controller could come back only after the arm had given up
        reconnect_attempts=50,
        reconnect_backoff_s=0.2,
    )
    robot.connect()
    try:
        wait_for(lambda: robot.state().connected and robot.state().t > 0, what="first state")
        robot.servo(np.array(Q0) + 0.2, np.zeros(6), robot.clock.now())
        fake.send("silent", True)  # the controller stops sending state: the link is dead
        wait_for(lambda: not robot.state().connected, what="loss detected")
        st = robot.state()
        assert "watchdog" in (st.fault or "")
        with pytest.raises(RobotConnectionError, match="watchdog"):
            robot.servo(np.array(Q0), np.zeros(6), robot.clock.now())
        # the state (shared memory) can show the loss before the worker's event crosses its queue
        wait_for(lambda: any(e["kind"] == "lost" for e in robot.events()), what="lost event")
        wait_for(lambda: fake.value(A_STOPS) >= 1, what="servoStop on loss")
        fake.send("silent", False)
        wait_for(lambda: robot.state().connected, what="reconnection")
        assert robot.connections == 2
        assert robot.state().protective_stop  # latched after a loss: the supervisor must reset
        robot.reset_protective_stop()
        wait_for(lambda: not robot.state().protective_stop, what="reset after reconnection")
    finally:
        robot.close()


def test_a_hung_worker_is_detected_and_killed() -> None:
    robot = RtdeRobot(
        "127.0.0.1",
        rate_hz=RATE_HZ,
        probe=False,
        hung_timeout_s=0.5,
        connect_timeout_s=20.0,
        receive_factory=blocking_receive_factory,
        control_factory=None,
    )
    robot.connect()
    try:
        pid = robot.worker_pid
        assert pid is not None
        wait_for(lambda: not robot.state().connected, what="hung worker detected")
        assert "stopped answering" in (robot.state().fault or "")
        assert robot.worker_pid is None
    finally:
        robot.close()


def test_silent_peer_gives_up_without_blocking_this_process() -> None:
    srv = _silent_listener()
    ticks = [0]
    stop = threading.Event()

    def count() -> None:
        while not stop.is_set():
            ticks[0] += 1
            time.sleep(0.005)

    counter = threading.Thread(target=count, daemon=True)
    counter.start()
    try:
        # Without the probe, ur_rtde's constructor blocks (holding the GIL) in the worker process.
        robot = _robot(srv.getsockname()[0], probe=False, connect_timeout_s=3.0)
        before = ticks[0]
        with pytest.raises(RobotConnectionError, match="did not complete"):
            robot.connect()
        assert ticks[0] - before > 20  # this process kept running while the worker was stuck
        assert robot.worker_pid is None  # the stuck worker was killed
        # With the probe (the default), the handshake times out first, with a clear message.
        robot = _robot(srv.getsockname()[0], connect_timeout_s=20.0)
        with pytest.raises(RobotConnectionError, match="did not answer the RTDE handshake"):
            robot.connect()
    finally:
        stop.set()
        srv.close()


def test_no_robot_at_the_address_is_a_clear_error() -> None:
    robot = _robot(free_loopback_address())
    with pytest.raises(RobotConnectionError, match=r"no robot at .*HRC_ROBOT_HOST"):
        robot.connect()
    with pytest.raises(RobotConnectionError, match="not connected"):
        robot.servo(np.array(Q0), np.zeros(6), 0.0)
