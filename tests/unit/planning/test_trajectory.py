from __future__ import annotations

import numpy as np
import pytest

from app.planning.trajectory import Plan, Trajectory, TrajectoryError, fit_knots

QD = np.full(6, np.pi)
QDD = np.full(6, 4.0)


def _plan(times: list[float], q: list[list[float]]) -> Plan:
    return Plan(times=np.array(times), q=np.array(q, dtype=float), nodes=np.arange(len(times)))


def _sampled(traj: Trajectory, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = traj.sample(dt)
    return t, traj.q(t), traj.qd(t), traj.qdd(t)


def test_plan_validates_shapes_and_order() -> None:
    with pytest.raises(TrajectoryError, match="shape"):
        Plan(times=np.zeros(2), q=np.zeros((3, 6)), nodes=np.zeros(2))
    with pytest.raises(TrajectoryError, match="non-decreasing"):
        _plan([1.0, 0.0], [[0] * 6, [1] * 6])
    with pytest.raises(TrajectoryError, match="NaN"):
        _plan([0.0, 1.0], [[0] * 6, [np.nan] * 6])
    p = _plan([0.0, 1.0], [[0] * 6, [1] * 6])
    assert p.duration == 1.0 and p.shifted(2.0).t_start == 2.0
    with pytest.raises(ValueError):
        p.q[0, 0] = 5.0  # read-only


def test_fit_passes_through_waypoints_within_limits_and_is_c1() -> None:
    q = [
        [0, 0, 0, 0, 0, 0],
        [0.6, -0.3, 0.2, 0, 0, 0.1],
        [1.0, -0.2, 0.5, 0.1, 0, 0.1],
        [0.8, 0.1, 0.5, 0.1, 0, 0],
    ]
    traj = Trajectory.from_plan(_plan([0.0, 0.3, 0.5, 0.8], q), qd_max=QD, qdd_max=QDD)
    np.testing.assert_allclose(traj.knot_q, np.array(q, dtype=float))
    np.testing.assert_allclose(traj.q(traj.knot_times), np.array(q, dtype=float), atol=1e-12)
    t, qs, qds, qdds = _sampled(traj)
    assert np.all(np.abs(qds) <= QD + 1e-9)
    assert np.all(np.abs(qdds) <= QDD + 1e-6)
    # C1: position and velocity continuous across knots (finite differences match qd)
    fd = np.diff(qs, axis=0) / np.diff(t)[:, None]
    mid = 0.5 * (qds[1:] + qds[:-1])
    assert np.max(np.abs(fd - mid)) < 1e-2
    # starts and ends at rest, holds after the end
    np.testing.assert_allclose(traj.qd(traj.t_start), 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.qd(traj.t_end + 1.0), 0.0)
    np.testing.assert_allclose(traj.q(traj.t_end + 5.0), q[-1])
    # retimed: slower than the infeasible waypoint times, never faster
    assert np.all(np.diff(traj.knot_times) >= np.diff([0.0, 0.3, 0.5, 0.8]) - 1e-12)


def test_monotone_no_overshoot_between_waypoints() -> None:
    q = [[0.0] * 6, [1.0] * 6, [1.5] * 6, [1.2] * 6]
    traj = Trajectory.from_plan(_plan([0.0, 1.0, 1.6, 2.6], q), qd_max=QD, qdd_max=QDD)
    knots = traj.knot_times
    for k in range(3):
        t = np.linspace(knots[k], knots[k + 1], 200)
        x = traj.q(t)[:, 0]
        lo, hi = sorted((q[k][0], q[k + 1][0]))
        assert x.min() >= lo - 1e-9 and x.max() <= hi + 1e-9


def test_waits_stay_still() -> None:
    q = [[0.0] * 6, [0.5] * 6, [0.5] * 6, [1.0] * 6]
    traj = Trajectory.from_plan(_plan([0.0, 1.0, 2.0, 3.0], q), qd_max=QD, qdd_max=QDD)
    t = np.linspace(traj.knot_times[1], traj.knot_times[2], 50)
    np.testing.assert_allclose(traj.q(t), 0.5, atol=1e-12)


def test_initial_velocity_is_continued_and_braked_within_limits() -> None:
    qd0 = np.array([1.0, -0.5, 0.0, 0.0, 0.0, 0.0])
    traj = Trajectory.from_plan(
        _plan([0.0, 0.5], [[0.0] * 6, [-0.3] + [0.0] * 5]), qd0=qd0, qd_max=QD, qdd_max=QDD
    )
    np.testing.assert_allclose(traj.qd(traj.t_start), qd0)
    _, _, qds, qdds = _sampled(traj)
    assert np.all(np.abs(qdds) <= QDD + 1e-6) and np.all(np.abs(qds) <= QD + 1e-9)
    # a single waypoint with a velocity brakes and comes back to it
    stay = Trajectory.from_plan(_plan([0.0], [[0.2] * 6]), qd0=qd0, qd_max=QD, qdd_max=QDD)
    assert stay.duration > 0.0
    np.testing.assert_allclose(stay.q(stay.t_end), [0.2] * 6)
    _, _, qds, qdds = _sampled(stay)
    assert np.all(np.abs(qdds) <= QDD + 1e-6)


def test_plan_with_knot_velocities_rebuilds_the_same_trajectory() -> None:
    traj = Trajectory.from_plan(
        _plan([0.0, 0.4, 1.0], [[0] * 6, [0.3] * 6, [0.1] * 6]), qd_max=QD, qdd_max=QDD
    )
    again = Trajectory.from_plan(traj.to_plan(), qd0=np.ones(6))  # qd0 ignored: the knots are fixed
    t = traj.sample(0.01)
    np.testing.assert_allclose(again.q(t), traj.q(t))
    np.testing.assert_allclose(again.qd(t), traj.qd(t))
    shifted = traj.shifted(1.5)
    np.testing.assert_allclose(shifted.q(t + 1.5), traj.q(t))


def test_scalar_and_vector_evaluation_and_tcp_needs_kinematics() -> None:
    traj = Trajectory.from_plan(_plan([0.0, 1.0], [[0] * 6, [1] * 6]), qd_max=QD, qdd_max=QDD)
    assert traj.q(0.5).shape == (6,) and traj.q(np.array([0.1, 0.2])).shape == (2, 6)
    with pytest.raises(TrajectoryError, match="kin"):
        traj.tcp(0.5)


def test_fit_knots_merges_duplicate_times() -> None:
    times, q, _ = fit_knots(
        np.array([0.0, 0.0, 1.0]), np.array([[0.0] * 6, [0.1] * 6, [0.5] * 6]), qd_max=QD, qdd_max=QDD
    )
    assert times.shape == (2,) and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(q[0], 0.0)


def test_state_equals_q_and_qd_at_one_time() -> None:
    rng = np.random.default_rng(4)
    times = np.array([0.0, 0.4, 0.9, 1.7])
    traj = Trajectory(times, rng.uniform(-1, 1, (4, 6)), rng.uniform(-0.5, 0.5, (4, 6)))
    for t in [-0.2, 0.0, 0.4, 0.41, 1.0, 1.7, 2.5, *rng.uniform(-0.5, 2.0, 50)]:
        q, qd = traj.state(t)
        np.testing.assert_allclose(q, traj.q(t), atol=1e-12)
        np.testing.assert_allclose(qd, traj.qd(t), atol=1e-12)
    still = Trajectory(np.array([0.0]), np.ones((1, 6)), np.zeros((1, 6)))
    q, qd = still.state(3.0)
    np.testing.assert_array_equal(q, np.ones(6))
    assert not qd.any()
