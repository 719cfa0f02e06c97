"""The simulated UR5e: tracking within limits, speed scale, stop and protective stop, either clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.cell.backends import make_robot
from app.cell.clock import SimClock
from app.cell.joint_tracking import JointLimits, JointTracker, ServoCommand
from app.cell.reference import ReferenceJointTracker
from app.cell.robot import RobotBackend, RobotConnectionError, RobotState, SimRobot
from app.config import Settings
from app.safety.stopping import MANUAL_DECEL_SHARE, UR5_MANUAL_JOINT_DECEL_RADPS2, UR5E_STOP

HOME = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
DT = 0.002


def _run(robot: SimRobot, clock: SimClock, seconds: float, dt: float = DT) -> list[RobotState]:
    out = []
    for _ in range(round(seconds / dt)):
        clock.advance(dt)
        out.append(robot.state())
    return out


def _check_limits(states: list[RobotState], limits: JointLimits, *, scale: float = 1.0) -> None:
    q = np.stack([s.q for s in states])
    qd = np.stack([s.qd for s in states])
    t = np.array([s.t for s in states])
    assert np.all(q >= limits.q_min - 1e-9) and np.all(q <= limits.q_max + 1e-9)
    assert np.all(np.abs(qd) <= scale * limits.qd_max + 1e-6)
    qdd = np.diff(qd, axis=0) / np.diff(t)[:, None]
    # a joint slows down within brake_decel and speeds up within qdd_max
    assert np.all(np.abs(qdd) <= limits.brake_decel + 1e-6)
    assert np.all(np.abs(qd[1:]) - np.abs(qd[:-1]) <= limits.qdd_max * np.diff(t)[:, None] + 1e-6)


def test_ur5e_limits_come_from_the_kinematics_module() -> None:
    from app.planning import kinematics

    lim = JointLimits.ur5e()
    np.testing.assert_array_equal(lim.q_max, kinematics.Q_MAX)
    np.testing.assert_array_equal(lim.qdd_max, kinematics.QDD_MAX)
    # it brakes as the manual's stops do (the stopping model counts on 60 % of that)
    np.testing.assert_array_equal(lim.brake_decel, UR5_MANUAL_JOINT_DECEL_RADPS2)
    assert np.all(lim.brake_decel * MANUAL_DECEL_SHARE >= np.asarray(UR5E_STOP.joint_decel_radps2) - 0.01)
    with pytest.raises(ValueError, match="brake_decel"):
        JointLimits(lim.q_min, lim.q_max, lim.qd_max, lim.qdd_max, brake_decel=lim.qdd_max / 2)


def test_a_joint_brakes_faster_than_it_may_speed_up() -> None:
    """Speeding up within qdd_max, slowing down within brake_decel: the supervisor's brake, commanded at
    the stopping model's deceleration, is followed without lag."""
    limits = JointLimits.ur5e()
    tracker = JointTracker(HOME, limits, max_substep_s=0.002)
    tracker.qd = np.array([2.0, 0, 0, 0, 0, 0])
    tracker.set_command(ServoCommand(0.0, tracker.q + np.array([0.02, 0, 0, 0, 0, 0]), np.zeros(6)))
    v0 = tracker.qd[0]
    tracker.step(0.0, 0.002)
    assert v0 - tracker.qd[0] == pytest.approx(limits.brake_decel[0] * 0.002)  # braking for the target
    tracker = JointTracker(HOME, limits, max_substep_s=0.002)
    tracker.set_command(ServoCommand(0.0, tracker.q + 1.0, np.zeros(6)))
    tracker.step(0.0, 0.002)
    np.testing.assert_allclose(tracker.qd, limits.qdd_max * 0.002)  # speeding up


def test_tracks_a_far_step_within_velocity_and_acceleration_limits() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    target = HOME + np.array([1.5, -0.5, 0.8, 0.3, -1.0, 3.0])
    robot.servo(target, np.zeros(6), clock.now())
    states = _run(robot, clock, 4.0)
    _check_limits(states, robot.limits)
    np.testing.assert_allclose(states[-1].q, target, atol=1e-3)
    assert np.all(np.abs(states[-1].qd) < 1e-2)
    # joint 5 moves 3 rad with 4 rad/s^2: a bang-bang profile would peak at sqrt(12) > pi, so it cruises at
    # the speed limit
    assert np.max(np.abs([s.qd[5] for s in states])) == pytest.approx(math.pi, abs=1e-6)
    # joint 5 cannot beat its limits: speeding up at 4 rad/s^2 (pi/4 s, pi^2/8 rad), braking at brake_decel,
    # cruising at pi rad/s between; the feedback's tail (kp = 12/s) settles it to 1 mrad within 0.5 s more
    a, b = 4.0, float(robot.limits.brake_decel[5])
    optimal = math.pi / a + math.pi / b + (3.0 - math.pi**2 / (2 * a) - math.pi**2 / (2 * b)) / math.pi
    arrived = next(s.t for s in states if abs(s.q[5] - target[5]) < 1e-3)
    assert optimal <= arrived <= optimal + 0.5


def test_follows_a_moving_set_point_closely() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    v = np.array([0.3, -0.2, 0.1, 0.0, 0.25, -0.4])
    errors = []
    for k in range(1500):  # 3 s at 500 Hz, the set-point moves at constant velocity
        t = clock.now()
        robot.servo(HOME + v * t, v, t)
        clock.advance(DT)
        if k > 500:
            errors.append(np.max(np.abs(robot.state().q - (HOME + v * clock.now()))))
    assert max(errors) < 2e-3


def test_speed_scale_caps_joint_speeds_and_keeps_the_path() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    robot.set_speed_scale(0.25)
    delta = np.array([1.0, 0.5, -0.5, 0.0, 0.0, 1.0])
    robot.servo(HOME + delta, np.zeros(6), clock.now())
    states = _run(robot, clock, 1.0)
    _check_limits(states, robot.limits, scale=0.25)
    assert states[-1].speed_scale == 0.25
    assert np.max(np.abs(states[-1].qd)) == pytest.approx(0.25 * math.pi, abs=1e-6)
    with pytest.raises(ValueError):
        robot.set_speed_scale(1.5)


def test_speed_scale_zero_brings_the_arm_to_rest_within_limits() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    robot.servo(HOME + 2.0, np.zeros(6), clock.now())
    _run(robot, clock, 0.6)
    assert np.max(np.abs(robot.state().qd)) > 1.0
    robot.set_speed_scale(0.0)
    states = _run(robot, clock, 1.0)
    _check_limits(states, robot.limits)
    assert np.all(states[-1].qd == 0.0)


def test_protective_stop_decelerates_within_limits_and_ignores_servo_until_reset() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    target = HOME + np.array([2.0, 1.0, -1.0, 0.5, 0.5, 2.0])
    robot.servo(target, np.zeros(6), clock.now())
    moving = _run(robot, clock, 0.7)
    qd0 = moving[-1].qd
    assert np.max(np.abs(qd0)) > 2.0
    robot.protective_stop()
    stopping = _run(robot, clock, 1.2)
    _check_limits([moving[-1], *stopping], robot.limits)
    assert stopping[-1].protective_stop
    assert np.all(stopping[-1].qd == 0.0)
    # all joints stop together: the stop takes max(|qd| / brake_decel) and the joint path is a straight line
    t_stop = np.max(np.abs(qd0) / robot.limits.brake_decel)
    n_moving = sum(1 for s in stopping if np.any(s.qd != 0))
    assert n_moving * DT == pytest.approx(t_stop, abs=2 * DT)
    dq = stopping[-1].q - moving[-1].q
    np.testing.assert_allclose(dq / np.linalg.norm(dq), qd0 / np.linalg.norm(qd0), atol=1e-3)
    # servo commands are ignored while stopped
    q_hold = stopping[-1].q.copy()
    robot.servo(target, np.zeros(6), clock.now())
    _run(robot, clock, 0.5)
    np.testing.assert_array_equal(robot.state().q, q_hold)
    assert robot.ignored_servo_commands == 1
    robot.reset_protective_stop()
    st = robot.state()
    assert not st.protective_stop
    np.testing.assert_array_equal(st.q, q_hold)  # the stale command is gone: it holds
    robot.servo(target, np.zeros(6), clock.now())
    _run(robot, clock, 3.0)
    np.testing.assert_allclose(robot.state().q, target, atol=1e-3)


def test_stop_comes_to_rest_then_accepts_new_commands() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    robot.servo(HOME + 1.0, np.zeros(6), clock.now())
    _run(robot, clock, 0.5)
    robot.stop()
    states = _run(robot, clock, 1.0)
    assert np.all(states[-1].qd == 0) and not states[-1].protective_stop
    robot.servo(HOME, np.zeros(6), clock.now())
    _run(robot, clock, 3.0)
    np.testing.assert_allclose(robot.state().q, HOME, atol=1e-3)


def test_targets_beyond_the_joint_limits_are_clipped() -> None:
    clock = SimClock()
    lim = JointLimits.ur5e()
    robot = SimRobot(clock, q0=np.zeros(6))
    robot.servo(np.array([0.0, 0.0, 3.5, 0.0, 0.0, 0.0]), np.zeros(6), clock.now())  # elbow limit is pi
    states = _run(robot, clock, 3.0)
    _check_limits(states, lim)
    assert states[-1].q[2] == pytest.approx(math.pi, abs=1e-3)
    assert max(s.q[2] for s in states) < math.pi


def test_lazy_sync_on_the_clock_equals_explicit_steps() -> None:
    clock_a, clock_b = SimClock(), SimClock()
    lazy = SimRobot(clock_a, q0=HOME)
    stepped = SimRobot(clock_b, q0=HOME)
    target = HOME + 0.8
    lazy.servo(target, np.zeros(6), 0.0)
    stepped.servo(target, np.zeros(6), 0.0)
    clock_a.advance(0.5)  # one jump on the clock
    for _ in range(125):
        stepped.step(0.004)  # explicit steps of the robot's own substep, the clock stays at 0
    np.testing.assert_allclose(lazy.state().q, stepped._tracker.q, atol=1e-9)


def test_a_stream_of_commands_that_stops_brings_the_arm_to_rest() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    v = np.full(6, 0.5)
    for _ in range(250):
        t = clock.now()
        robot.servo(HOME + v * t, v, t)
        clock.advance(DT)
    _run(robot, clock, 1.0)  # no more commands: extrapolates 0.1 s, then holds
    st = robot.state()
    assert np.all(np.abs(st.qd) < 1e-3)
    np.testing.assert_allclose(st.q, HOME + v * (0.5 + 0.1), atol=2e-3)


def test_closed_robot_refuses_commands_and_bad_commands_raise() -> None:
    clock = SimClock()
    robot = SimRobot(clock, q0=HOME)
    with pytest.raises(ValueError, match="shape"):
        robot.servo(np.zeros(5), np.zeros(6), 0.0)
    with pytest.raises(ValueError, match="finite"):
        robot.servo(np.full(6, np.nan), np.zeros(6), 0.0)
    robot.close()
    assert not robot.state().connected
    with pytest.raises(RobotConnectionError):
        robot.servo(HOME, np.zeros(6), 0.0)


def test_make_robot_sim_is_a_backend() -> None:
    robot = make_robot(Settings(robot="sim"), SimClock(), q0=HOME)
    assert isinstance(robot, SimRobot)
    assert isinstance(robot, RobotBackend)
    st = robot.state()
    assert st.connected and not st.protective_stop and st.speed_scale == 1.0
    np.testing.assert_allclose(st.q, HOME)
    with pytest.raises(ValueError):
        RobotState(0.0, np.zeros(5), np.zeros(6), False, 1.0, True)


def test_tracker_reference_extrapolates_then_holds() -> None:
    tracker = JointTracker(HOME, JointLimits.ur5e(), hold_after_s=0.1)
    tracker.set_command(ServoCommand(1.0, HOME, np.full(6, 0.2)))
    q, qd = tracker.reference(1.05)
    np.testing.assert_allclose(q, HOME + 0.01)
    np.testing.assert_allclose(qd, 0.2)
    q, qd = tracker.reference(5.0)
    np.testing.assert_allclose(q, HOME + 0.02)
    np.testing.assert_array_equal(qd, 0.0)


def test_sim_robot_steps_on_the_wall_clock_without_a_thread() -> None:
    from app.cell.clock import WallClock

    clock = WallClock()
    robot = SimRobot(clock, q0=HOME)
    first = robot.state()
    robot.servo(HOME + 0.5, np.zeros(6), clock.now())
    for _ in range(200):  # bounded: the arm moves as real time passes
        st = robot.state()
        if np.any(st.q != HOME):
            break
        clock.sleep_until(clock.now() + 0.005)
    assert st.t > first.t
    assert np.all(st.q >= HOME) and np.any(st.q > HOME)


@pytest.mark.parametrize("stopping", [False, True])
def test_the_compiled_tracker_equals_the_numpy_reference(stopping: bool) -> None:
    """The compiled integration loop follows the NumPy reference step for step: tracking commands that
    lead, lag, expire and hit the joint limits, at several speed scales, and braking to rest."""
    rng = np.random.default_rng(3 if stopping else 4)
    limits = JointLimits.ur5e()
    a = JointTracker(HOME, limits, hold_after_s=0.1, max_substep_s=0.004)
    b = ReferenceJointTracker(HOME, limits, hold_after_s=0.1, max_substep_s=0.004)
    t = 0.0
    for k in range(400):
        if k % 25 == 0:
            q = np.asarray(HOME) + rng.uniform(-1.0, 1.0, 6)
            if k % 100 == 0:
                q[1] = limits.q_max[1] + 0.5  # beyond the limit: clipped inside it
            lead = rng.uniform(-0.05, 0.05)
            cmd = None if k % 75 == 0 else ServoCommand(t + lead, q, rng.uniform(-2, 2, 6))
            a.set_command(cmd)
            b.set_command(cmd)
        dt = float(rng.choice([0.008, 0.002, 0.0131, 0.0]))
        scale = float(rng.choice([1.0, 0.5, 0.05, 0.0]))
        brake = stopping and k >= 200
        a.step(t, dt, speed_scale=scale, stopping=brake)
        b.step(t, dt, speed_scale=scale, stopping=brake)
        t += dt
        np.testing.assert_allclose(a.q, b.q, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.qd, b.qd, rtol=0, atol=1e-12)
    assert np.all(a.q >= limits.q_min) and np.all(a.q <= limits.q_max)
    if stopping:
        assert a.at_rest
