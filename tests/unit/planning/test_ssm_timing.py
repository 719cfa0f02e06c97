"""SSM-aware timing: a plan verified at the timing the speed governor will give it.

The governor's model (:class:`app.safety.governor.GovernorModel`) predicts the supervisor's scale from a
forecast; :func:`app.planning.ssm_timing.predicted_scales` walks a path at it, the planner verifies the path
at that timing (:class:`app.planning.ssm_timing.PredictedTiming`) and reports the predicted arrival, and the
search (``PlannerConfig.ssm_aware_search``) asks of a fast move the clearance that the governor needs to let
it run fast. The UR5e tests use the real collision model; the search tests the point robot of
``test_search``.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable

import numpy as np
import pytest

from app.config import load_workcell
from app.planning.collision import CollisionModel
from app.planning.search import Planner
from app.planning.ssm_timing import PredictedTiming, predicted_scales
from app.planning.trajectory import Trajectory
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame
from app.safety.governor import GovernorModel, SeparationModel, SpeedScaleLaw
from app.safety.ssm import SSMParams
from app.safety.stopping import UR5E_STOP
from tests.governor_reference import predicted_scales_reference
from tests.unit.planning.test_search import R_HUMAN, R_ROBOT, PointRobot, config, person, q_of, roadmap

SEPARATION = SeparationModel(
    s0_m=0.11, t_reaction_s=0.11, stop_decel_mps2=3.0, human_speed_max_mps=2.0, human_accel_mps2=8.0
)


def governor(**kw: object) -> GovernorModel:
    base = dict(
        separation=SEPARATION,
        brake_decel_mps2=3.0,
        brake_joint_decel=UR5E_STOP.slowest_joint_decel_radps2,
        tracking_margin_m=0.02,
        speed_window_s=0.1,
        sensing_age_s=0.09,
        lookahead_s=0.6,
    )
    base.update(kw)
    return GovernorModel(**base)  # type: ignore[arg-type]


@pytest.fixture(scope="module")
def ur5e() -> CollisionModel:
    return CollisionModel(load_workcell())


def _base_turn(duration_s: float) -> Trajectory:
    """The UR5e at home turning its base by 1 rad at rest at both ends."""
    q0 = np.array([0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
    q1 = q0.copy()
    q1[0] = -1.0
    t = np.linspace(0.0, duration_s, 5)
    s = 0.5 - 0.5 * np.cos(np.pi * t / duration_s)  # smooth from rest to rest
    q = q0 + s[:, None] * (q1 - q0)
    qd = (0.5 * np.pi / duration_s) * np.sin(np.pi * t / duration_s)[:, None] * (q1 - q0)
    return Trajectory(t, q, qd)


def _standing(at: np.ndarray) -> HumanForecast:
    joints = (
        np.tile(np.asarray(at, dtype=float), (NUM_JOINTS, 1)) + np.linspace(0.0, 1e-3, NUM_JOINTS)[:, None]
    )
    return HumanForecast.hold(HumanFrame(0.0, joints))


def test_nobody_near_leaves_the_plan_at_full_speed(ur5e: CollisionModel) -> None:
    traj = _base_turn(1.0)
    fc = _standing(np.array([6.0, 0.0, 0.5]))
    _, t, scales = predicted_scales(traj, fc, ur5e, governor())
    assert np.all(scales == 1.0)
    assert t[-1] == pytest.approx(traj.t_end)
    view = PredictedTiming.of(traj, fc, ur5e, governor())
    assert view.t_end == pytest.approx(traj.t_end)
    ts = np.linspace(0.0, 1.0, 11)
    assert np.allclose(view.q(ts), traj.q(ts))


@pytest.mark.timeout(60)
def test_a_path_of_no_duration_is_timed_at_once(ur5e: CollisionModel) -> None:
    """A path that starts where it ends (one knot: the robot already at its goal) looks ahead over its one
    point, not over the look-ahead's ~1e8 steps of zero length (a trial with a passer-by hung there)."""
    q0 = np.array([[0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]])
    traj = Trajectory(np.array([2.0]), q0, np.zeros((1, 6)))
    tau, t, scales = predicted_scales(traj, _standing(np.array([0.6, 0.0, 0.5])), ur5e, governor())
    assert tau.shape == (2,) and t[0] == pytest.approx(2.0) and scales.shape == (1,)
    assert np.all(np.isfinite(t))


def test_a_person_beside_the_path_slows_the_predicted_timing_along_the_same_path(
    ur5e: CollisionModel,
) -> None:
    traj = _base_turn(1.0)
    model = governor()
    fc = _standing(np.array([0.9, -0.3, 0.2]))  # in front of the arm, beside the turn
    tau, t, scales = predicted_scales(traj, fc, ur5e, model)
    assert t[-1] - t[0] > 1.25 * traj.duration  # the governor would slow this turn
    assert np.all(np.diff(t) >= np.diff(tau) - 1e-12)  # never faster than the path's own timing
    view = PredictedTiming.of(traj, fc, ur5e, model)
    assert view.t_end == pytest.approx(t[-1])
    # the same path: at the predicted wall time of each point the view is where the trajectory is at its
    # own time
    assert np.allclose(view.q(t), traj.q(tau), atol=1e-9)
    assert view.base_trajectory is traj and np.allclose(view.path_times(t), tau)
    # slowest where the person is nearest
    sep = np.array([ur5e.pair_distances(q, fc.joints[:1])[0].min() for q in traj.q(tau[:-1])])
    assert scales[np.argmin(sep)] <= np.median(scales)
    # a floor: where no speed at all is safe the path is timed at the smallest scale, never forever
    _, _, none_safe = predicted_scales(traj, _standing(np.array([0.3, -0.2, 0.4])), ur5e, model)
    assert none_safe.min() == model.min_scale


def _walking_past(t0: float) -> HumanForecast:
    """A person walking past the front of the arm at 1.2 m/s, one pose every 80 ms for a second, swinging
    a hand toward the robot."""
    times = t0 + np.arange(13) * 0.08
    base = np.array([1.1, -0.6, 0.2]) + np.linspace(0.0, 1e-3, NUM_JOINTS)[:, None]
    joints = np.stack(
        [base + np.array([-0.2 * np.sin(4 * k * 0.08), 1.2 * k * 0.08, 0.0]) for k in range(13)]
    )
    return HumanForecast(t0=t0, times=times, joints=joints, margins=np.zeros(13))


@pytest.mark.parametrize("law", [False, True])
@pytest.mark.parametrize("t0", [0.0, 0.5])
def test_the_compiled_walk_matches_its_numpy_reference(ur5e: CollisionModel, law: bool, t0: float) -> None:
    """Along a path past a walking person (the forecast starts at ``t0``, so the walk also reads it held
    before its start), with and without the speed-scaling law: the same times and scales to rounding."""
    traj = _base_turn(1.5)
    model = governor(speed_noise_mps=0.3, law=SpeedScaleLaw(SSMParams()) if law else None)
    fc = _walking_past(t0)
    tau, t, scales = predicted_scales(traj, fc, ur5e, model)
    tau_r, t_r, scales_r = predicted_scales_reference(traj, fc, ur5e, model)
    assert np.array_equal(tau, tau_r)
    assert scales.min() < 0.7  # the person matters here
    assert np.allclose(scales, scales_r, rtol=0, atol=1e-9)
    assert np.allclose(t, t_r, rtol=1e-9, atol=1e-9)


def test_the_extra_clearance_is_zero_up_to_the_creep_and_grows_with_speed() -> None:
    extra = governor(speed_noise_mps=0.3).extra_clearance(v_creep_mps=0.15, decel_mps2=1.5)
    v = np.arange(extra.size) * 0.05
    assert np.all(extra[v <= 0.15] == 0.0)
    assert np.all(np.diff(extra) >= 0.0)
    assert extra[v.searchsorted(1.0)] > 0.5  # at 1 m/s the governor needs half a metre more than a creep


def test_a_noisier_person_or_an_older_frame_slows_the_prediction(ur5e: CollisionModel) -> None:
    traj = _base_turn(1.0)
    fc = _standing(np.array([1.0, -0.3, 0.2]))
    base = predicted_scales(traj, fc, ur5e, governor())[1][-1]
    assert predicted_scales(traj, fc, ur5e, governor(speed_noise_mps=0.3))[1][-1] > base
    assert predicted_scales(traj, fc, ur5e, governor(sensing_age_s=0.2))[1][-1] > base


def test_governor_model_rejects_bad_settings() -> None:
    with pytest.raises(ValueError, match="min_scale"):
        governor(min_scale=0.0)
    with pytest.raises(ValueError, match="speed_window_s"):
        governor(speed_window_s=0.0)
    with pytest.raises(ValueError, match="sensing_age_s"):
        governor(sensing_age_s=-0.1)


class PairedPointRobot(PointRobot):
    """The point robot of ``test_search`` with the per-part distances of the SSM timing."""

    def pair_distances(self, q: np.ndarray, joints: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(np.asarray(joints) - np.asarray(q)[:3], axis=-1)  # (P, J)
        return (d - R_ROBOT - R_HUMAN)[:, None, :]


def test_the_search_goes_round_a_person_where_creeping_past_would_arrive_later() -> None:
    # short way s - m - g (2 s at full speed) passes 0.3 m from a person standing beside m; the long way
    # s - d1 - d2 - g (4.4 s) stays 0.9 m away
    rm = roadmap(
        [(0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (0.0, 0.8), (1.0, 0.8)],
        [(0, 1), (1, 2), (0, 3), (3, 4), (4, 2)],
        s=0,
        g=2,
    )
    fc = person([0.0], [(0.5, -0.5)])
    robot = PairedPointRobot()
    model = governor(tracking_margin_m=0.0, lookahead_s=0.2)
    plain = Planner(rm, robot, config=config(shortcut=False, ssm_aware_search=False))
    aware = Planner(rm, robot, config=config(shortcut=False, ssm_aware_search=True, ssm_brake_decel_mps2=3.0))
    a = plain.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc, timing=model)
    b = aware.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc, timing=model)
    assert a.ok and b.ok, (a.reason, b.reason)
    assert [n for n in a.plan.nodes.tolist() if n >= 0] == [0, 1, 2]
    assert [n for n in b.plan.nodes.tolist() if n >= 0] == [0, 3, 4, 2]
    # both report the arrival the governor will allow: the long way arrives first, though its own timing
    # (at full speed) is longer
    assert b.arrival_s < a.arrival_s
    assert b.trajectory.t_end > a.trajectory.t_end
    for res in (a, b):
        _, t, _ = predicted_scales(res.trajectory, fc, robot, model)
        assert res.arrival_s == pytest.approx(t[-1])
    # without the governor's model the arrival is the trajectory's own end
    c = plain.plan(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc)
    assert c.arrival_s == pytest.approx(c.trajectory.t_end)


def test_where_the_governors_clearance_leaves_no_plan_the_search_falls_back_to_the_plain_clearance() -> None:
    # the only way s - m - g passes 0.3 m from a person standing beside m (two dead ends leave s too);
    # this robot cannot creep (no slower speeds), so with the clearance the governor needs for a move at
    # its speed there is no plan at all, and without it the robot passes at its cruise speed (the
    # governor then slows it)
    rm = roadmap(
        [(0.0, 0.0), (1.0, 0.0), (2.0, 0.0), (0.0, 0.5), (-0.5, 0.0)],
        [(0, 1), (1, 2), (0, 3), (0, 4)],
        s=0,
        g=2,
    )
    fc = person([0.0], [(1.0, -0.3)])
    robot = PairedPointRobot()
    model = governor(tracking_margin_m=0.0, lookahead_s=0.2)
    kw = dict(shortcut=False, ssm_aware_search=True, ssm_brake_decel_mps2=3.0)
    query = dict(q_start=q_of(0, 0), t_start=0.0, goal="g", forecast=fc, timing=model, deadline_s=1.0)

    def ticks() -> Callable[[], float]:  # a planner clock that advances 1 ms per reading
        count = itertools.count()
        return lambda: next(count) * 1e-3

    only_aware = Planner(rm, robot, config=config(**kw, ssm_fallback_share=1.0), timer=ticks()).plan(**query)
    assert not only_aware.ok and only_aware.expanded > 0
    res = Planner(rm, robot, config=config(**kw, ssm_fallback_share=0.5), timer=ticks()).plan(**query)
    plain_cfg = config(shortcut=False, ssm_aware_search=False)
    plain = Planner(rm, robot, config=plain_cfg, timer=ticks()).plan(**query)
    assert res.ok and plain.ok, (res.reason, plain.reason)
    assert res.plan.nodes.tolist() == plain.plan.nodes.tolist()
    np.testing.assert_allclose(res.plan.q, plain.plan.q)
    np.testing.assert_allclose(res.plan.times, plain.plan.times)
    assert res.arrival_s == pytest.approx(plain.arrival_s)
    # both searches' expansions and times are counted: the first is the one that found nothing
    assert res.expanded == only_aware.expanded + plain.expanded
    assert res.phases_s["search"] == pytest.approx(only_aware.phases_s["search"] + plain.phases_s["search"])
    assert res.phases_s["finish"] == pytest.approx(plain.phases_s["finish"])
    assert res.phases_s["finish"] > 0
    with pytest.raises(ValueError, match="ssm_fallback_share"):
        config(ssm_fallback_share=0.0)
