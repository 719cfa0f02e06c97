"""Every trajectory the planner returns, sampled at 100 Hz, is within the joint limits, clear of the static
scene and keeps the required separation from the forecast it was planned against.

The check below is independent of the planner's code path: it evaluates the trajectory itself, takes the robot
speed from numerical derivatives of the capsule points, the distances from the collision model's exact
capsule distance, and the requirement from :func:`app.safety.ssm.forecast_clearance`.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from app.config import load_workcell
from app.planning.collision import CollisionModel
from app.planning.kinematics import Q_MAX, Q_MIN
from app.planning.roadmap import RoadmapConfig, load_or_build_roadmap
from app.planning.scenarios import reference_queries, synthetic_forecast
from app.planning.search import Planner
from app.planning.trajectory import Trajectory
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS
from app.safety.ssm import SSMParams, forecast_clearance
from app.safety.stopping import UR5E_STOP


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    cell = load_workcell()
    model = CollisionModel(cell)
    rm = load_or_build_roadmap(
        cell, config=RoadmapConfig(num_nodes=300), cache_dir=tmp_path_factory.mktemp("rm"), collision=model
    )
    return cell, model, rm, Planner(rm, model)


def violations(
    traj: Trajectory, forecast: HumanForecast | None, model: CollisionModel, ssm: SSMParams, *, hold_s: float
) -> list[str]:
    t = np.arange(traj.t_start, traj.t_end + hold_s + 1e-9, 0.01)
    q = traj.q(t)
    out = []
    if np.any(q < Q_MIN - 1e-9) or np.any(q > Q_MAX + 1e-9):
        out.append("joint limits")
    moving = (t >= traj.t_start) & (t <= traj.t_end)
    if np.any(model.static_clearance(q[moving]) < 0.0) or np.any(model.self_collision(q[moving])):
        out.append("static scene or self-collision")
    if forecast is not None:
        eps = 1e-5
        q0, q1 = traj.q(t - eps), traj.q(t + eps)
        a0, b0, _ = model.robot_capsules(q0)
        a1, b1, _ = model.robot_capsules(q1)
        v = np.maximum(np.linalg.norm(a1 - a0, axis=-1), np.linalg.norm(b1 - b0, axis=-1)).max(axis=1) / (
            2 * eps
        )
        w = UR5E_STOP.braking_speed((q1 - q0) / (2 * eps))  # the joints' share of the stopping model's T_s
        joints, margins = forecast.poses_at(t)
        d = model.distance_to_human_paired(q, joints)
        need = forecast_clearance(v, margins, ssm, w_top_radps=w)
        bad = np.flatnonzero(d < need - 1e-9)
        if bad.size:
            k = bad[0]
            out.append(f"separation at t={t[k] - traj.t_start:.2f}: {d[k]:.3f} < {need[k]:.3f}")
    return out


def test_planned_trajectories_are_valid_at_100_hz(setup: tuple) -> None:
    cell, model, rm, planner = setup
    ssm, hold = planner.config.ssm, planner.config.goal_hold_s
    queries = reference_queries(cell, rm, n=8, seed=3)
    ok = 0
    for qr in queries:
        static = planner.plan(q_start=qr.q_start, t_start=qr.t_start, goal=qr.goal, forecast=None)
        assert static.ok, (qr.name, static.reason)
        assert not violations(static.trajectory, None, model, ssm, hold_s=0.0)
        for workers in (1, 8):
            res = planner.plan(
                q_start=qr.q_start, t_start=qr.t_start, goal=qr.goal, forecast=qr.forecast, workers=workers
            )
            if not res.ok:
                assert res.plan is None and res.trajectory is None and res.reason
                continue
            ok += 1
            assert res.trajectory.t_start == pytest.approx(qr.t_start)
            np.testing.assert_allclose(res.trajectory.q(qr.t_start), qr.q_start, atol=1e-9)
            # the plan rebuilds exactly the verified trajectory
            again = Trajectory.from_plan(res.plan)
            ts = res.trajectory.sample(0.05)
            np.testing.assert_allclose(again.q(ts), res.trajectory.q(ts))
            assert not violations(res.trajectory, qr.forecast, model, ssm, hold_s=hold), qr.name
    assert ok >= 8  # most of the reference queries are feasible (16 searches)


def test_replanning_from_a_moving_robot_is_continuous_and_valid(setup: tuple) -> None:
    cell, model, rm, planner = setup
    ssm, hold = planner.config.ssm, planner.config.goal_hold_s
    first = planner.plan(
        q_start=rm.ik[rm.station_nodes["home"]][rm.valid[rm.station_nodes["home"]]][0],
        t_start=0.0,
        goal="A_approach",
        forecast=None,
    )
    assert first.ok
    traj = first.trajectory
    t_switch = traj.t_start + 0.4 * traj.duration
    q0, qd0 = traj.q(t_switch), traj.qd(t_switch)
    assert np.linalg.norm(qd0) > 0.05  # really moving
    fc = synthetic_forecast(cell, seed=11, t0=t_switch - 0.1, reach=False)
    res = planner.plan(q_start=q0, t_start=t_switch, goal="D_approach", forecast=fc, qd0=qd0, workers=8)
    assert res.ok, res.reason
    np.testing.assert_allclose(res.trajectory.q(t_switch), q0, atol=1e-9)
    np.testing.assert_allclose(res.trajectory.qd(t_switch), qd0, atol=1e-9)
    assert not violations(res.trajectory, fc, model, ssm, hold_s=hold)


def test_emergency_plans_are_valid_against_the_held_person(setup: tuple) -> None:
    cell, model, rm, planner = setup
    ssm = planner.config.ssm
    horizon = 1 / 30 + 0.1
    for qr in reference_queries(cell, rm, n=10, seed=5):
        res = planner.emergency(
            q_start=qr.q_start, t_start=qr.t_start, forecast=qr.forecast, horizon_s=horizon
        )
        joints, margin = qr.forecast.pose_at(qr.t_start)
        held = HumanForecast(
            t0=qr.t_start,
            times=np.array([qr.t_start]),
            joints=joints[None],
            margins=np.array([margin]),
            growth_mps=qr.forecast.growth_mps,
            max_margin_m=qr.forecast.max_margin_m,
        )
        d0 = float(model.distance_to_human_paired(qr.q_start[None], joints[None])[0])
        if not res.ok:
            assert res.plan is None
            continue
        assert res.trajectory.t_end >= qr.t_start
        if d0 >= forecast_clearance(0.0, margin, ssm, w_top_radps=0.0):
            assert not violations(res.trajectory, held, model, ssm, hold_s=horizon), qr.name
        else:  # escaping: never closer to the person than at the start
            t = np.arange(res.trajectory.t_start, res.trajectory.t_end + 1e-9, 0.01)
            d = model.distance_to_human_paired(res.trajectory.q(t), np.repeat(joints[None], t.size, axis=0))
            assert np.all(d >= d0 - 1e-3)


def station_q(rm, name: str) -> np.ndarray:
    """The first valid stored IK branch of a station (angles as IK returns them, in [-pi, pi])."""
    n = rm.station_nodes[name]
    return rm.ik[n][rm.valid[n]][0]


@pytest.mark.parametrize(
    ("start", "goal"), [("pickup_approach", "D_approach"), ("D_approach", "pickup_approach")]
)
def test_the_base_turns_the_short_way_across_the_wrap_of_the_stored_angles(
    setup: tuple, start: str, goal: str
) -> None:
    _, model, rm, planner = setup
    q_start = station_q(rm, start)
    g = rm.station_nodes[goal]
    stored = rm.ik[g][rm.valid[g]]
    # the arm's family of branches is split at +-pi: stored base angles 1.69 (pickup) vs -2.81 (D), 4.5 apart
    same_family = stored[np.argmin(np.abs(stored[:, 1:] - q_start[1:]).max(axis=1))]
    assert abs(same_family[0] - q_start[0]) > math.pi
    res = planner.plan(q_start=q_start, t_start=0.0, goal=goal, forecast=None)
    assert res.ok, res.reason
    q = res.trajectory.q(res.trajectory.sample(0.01))
    # arrives at a 2 pi-equivalent of a stored goal branch, turning the base the short way (1.8 rad)
    d = q[-1] - stored
    assert np.min(np.abs(d - 2 * math.pi * np.rint(d / (2 * math.pi))).max(axis=1)) < 1e-6
    short = abs((q[-1, 0] - q[0, 0] + math.pi) % (2 * math.pi) - math.pi)
    assert short < 2.0
    assert abs(q[-1, 0] - q[0, 0]) == pytest.approx(short, abs=1e-6)
    assert np.abs(np.diff(q[:, 0])).sum() <= short + 0.05  # no back and forth on the way either
    assert not violations(res.trajectory, None, model, planner.config.ssm, hold_s=0.0)


def test_shortcut_plans_are_faster_than_the_search_paths_and_valid(setup: tuple) -> None:
    cell, model, rm, planner = setup
    raw = Planner(rm, model, config=dataclasses.replace(planner.config, shortcut=False))
    ssm, hold = planner.config.ssm, planner.config.goal_hold_s
    aside = synthetic_forecast(cell, seed=11, t0=0.0, reach=False)
    for start, goal in (("pickup_approach", "A_approach"), ("pickup_approach", "D_approach")):
        for forecast in (None, aside):
            res = planner.plan(q_start=station_q(rm, start), t_start=0.0, goal=goal, forecast=forecast)
            ref = raw.plan(q_start=station_q(rm, start), t_start=0.0, goal=goal, forecast=forecast)
            assert res.ok and ref.ok, (res.reason, ref.reason)
            if forecast is None:  # on a free way the shortcut always shortens
                assert res.plan.q.shape[0] < ref.plan.q.shape[0]
                assert res.trajectory.duration < 0.7 * ref.trajectory.duration, (start, goal)
            else:  # beside a person it may give up (a re-timed move meets the person): never worse
                assert res.plan.q.shape[0] <= ref.plan.q.shape[0]
                assert res.trajectory.duration <= ref.trajectory.duration + 1e-9, (start, goal)
            assert not violations(res.trajectory, forecast, model, ssm, hold_s=hold), (start, goal)
            np.testing.assert_allclose(res.trajectory.q(0.0), station_q(rm, start), atol=1e-9)


def test_a_person_on_the_direct_move_is_not_cut_through(
    setup: tuple, tmp_path_factory: pytest.TempPathFactory
) -> None:
    cell, model, _, _ = setup
    # the way round keeps the robot's stop by the stopping model at cruise speed (0.3 m at 1.2 m/s): it needs
    # a roadmap denser than the other tests' 300 nodes (the shipped one has 1000)
    rm = load_or_build_roadmap(
        cell, config=RoadmapConfig(num_nodes=600), cache_dir=tmp_path_factory.mktemp("rm600"), collision=model
    )
    planner = Planner(rm, model)
    q_start = station_q(rm, "pickup_approach")
    direct = planner.plan(q_start=q_start, t_start=0.0, goal="D_approach", forecast=None)
    assert direct.ok and direct.plan.q.shape[0] == 2  # nothing in the way: one straight move
    tr = direct.trajectory
    p_mid = model.kin.fk_tcp(tr.q(0.5 * (tr.t_start + tr.t_end))[None])[0, :3, 3]
    # a person (every joint at one point) standing where the straight move's tool passes halfway
    fc = HumanForecast(
        t0=0.0, times=np.array([0.0]), joints=np.tile(p_mid, (1, NUM_JOINTS, 1)), margins=np.zeros(1)
    )
    res = planner.plan(q_start=q_start, t_start=0.0, goal="D_approach", forecast=fc, workers=8)
    assert res.ok, res.reason
    assert res.plan.q.shape[0] > 2
    assert not violations(res.trajectory, fc, model, planner.config.ssm, hold_s=planner.config.goal_hold_s)
