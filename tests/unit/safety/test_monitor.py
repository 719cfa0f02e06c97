"""The ground-truth monitor and the stopping model: planted unsafe motions are caught, a robot at rest is
never blamed, episodes end at standstill, and the ISO 13855 variant judges with constant speeds."""

from __future__ import annotations

import numpy as np
import pytest

from app.config import load_workcell
from app.control.engine import CellGeometry
from app.planning.collision import HUMAN_CAPSULES, ROBOT_LINKS, CollisionModel
from app.prediction.skeleton import NUM_JOINTS
from app.safety.monitor import GroundTruthMonitor
from app.safety.ssm import SSMParams
from app.safety.stopping import UR5E_STOP, StoppingModel, reaction_time_s

T_R = 0.111


@pytest.fixture(scope="module")
def geometry() -> CellGeometry:
    return CellGeometry(CollisionModel(load_workcell()))


def _monitor(geometry: CellGeometry) -> GroundTruthMonitor:
    return GroundTruthMonitor(
        geometry, SSMParams(), part_names=ROBOT_LINKS, human_capsules=HUMAN_CAPSULES, reaction_time_s=T_R
    )


def _scene(geometry: CellGeometry, gap_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The robot at home turning its base, and a person (a small cluster of joints) ``gap_m`` ahead of the
    tool's motion (surface to surface, about). Returns q, qd, the person and the tool's direction."""
    q = np.asarray(load_workcell().robot.home_q, dtype=float)
    qd = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    _a0, b0, _ = geometry.collision.robot_capsules(q[None])
    _a1, b1, _ = geometry.collision.robot_capsules((q + 1e-3 * qd)[None])
    tool = ROBOT_LINKS.index("tool")
    tip, tip1 = b0[0, tool], b1[0, tool]
    direction = (tip1 - tip) / np.linalg.norm(tip1 - tip)
    person = np.tile(tip + 0.6 * direction, (NUM_JOINTS, 1)) + np.linspace(0.0, 1e-3, NUM_JOINTS)[:, None]
    for _ in range(3):  # slide the person along the tool's motion until the separation is gap_m
        person = person - (geometry.separation(q, person) - gap_m) * direction
    assert geometry.separation(q, person) == pytest.approx(gap_m, abs=1e-3)
    return q, qd, person, direction


def test_a_robot_moving_toward_a_person_inside_sp_is_a_violation_and_touching_is_a_contact(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, _direction = _scene(geometry, 0.15)
    sample = mon.check(0.0, q, qd, person, person, 0.008)
    assert sample.violation and not sample.contact
    assert sample.robot_speed_mps > 0.3  # toward the person
    assert sample.separation_m < sample.required_m
    # S_p = v_r T_r + S_s + C + Z_r (the person stands still; Z_d is not added on the truth)
    ssm = SSMParams()
    v_top = float(geometry.part_speeds(q, qd).max())
    t_s = UR5E_STOP.stop_time_s(v_top, 1.0)
    expected = sample.robot_speed_mps * (T_R + t_s / 2) + ssm.intrusion_m + ssm.z_robot_m
    assert sample.required_m == pytest.approx(expected, rel=1e-6)
    # the same robot touching the person: a contact (and still one violation episode)
    q2, qd2, person2, _ = _scene(geometry, -0.02)
    touch = mon.check(0.008, q2, qd2, person2, person2, 0.008)
    assert touch.contact and touch.violation
    totals = mon.totals()
    assert totals.violations == 1 and totals.contacts == 1 and totals.violation_time_s == pytest.approx(0.008)
    assert totals.worst is not None and totals.worst.separation_m < 0


def test_a_robot_at_standstill_is_never_blamed_and_standstill_ends_an_episode(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, -0.02)
    rushing = person - 0.02 * direction  # the person came 2 cm closer in 8 ms: 2.5 m/s
    still = mon.check(0.0, q, np.zeros(6), person, rushing, 0.008)
    assert not still.violation and not still.contact
    creeping = mon.check(0.008, q, np.full(6, 0.005), person, person, 0.008)  # below 0.01 rad/s
    assert not creeping.violation
    assert mon.violations == 0 and mon.min_separation_moving_m == np.inf
    assert mon.min_separation_m < 0
    # moving: one episode per approach, ended by the standstill in between
    for t in (0.016, 0.024):
        mon.check(t, q, qd, person, person, 0.008)
    mon.check(0.032, q, np.zeros(6), person, person, 0.008)
    mon.check(0.040, q, qd, person, person, 0.008)
    assert mon.violations == 2 and mon.contacts == 2


def test_a_robot_moving_away_from_a_still_person_keeps_only_the_constant_terms(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, _ = _scene(geometry, 0.08)
    away = mon.check(0.0, q, -qd, person, person, 0.008)
    assert away.robot_speed_mps == 0.0 and away.human_speed_mps == 0.0
    ssm = SSMParams()
    assert away.required_m == pytest.approx(ssm.intrusion_m + ssm.z_robot_m)
    assert not away.violation
    # ISO 13855's constant speeds ask for 2.0 m/s x (T_r + T_s) more for the arm capsules: a violation
    assert mon.violations_iso == 1


def test_the_person_approaching_a_robot_part_raises_its_sp(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, 0.25)
    before = person + 0.01 * direction  # 1 cm farther 8 ms ago: 1.25 m/s toward the tool
    sample = mon.check(0.0, q, -qd, person, before, 0.008)
    assert sample.human_speed_mps == pytest.approx(1.25, rel=0.05)
    assert sample.violation  # 1.25 m/s x (T_r + T_s) + C + Z_r > 0.25 m


def test_the_stopping_model() -> None:
    m = StoppingModel(decel_mps2=3.0, joint_decel_radps2=3.0, delay_s=0.0)
    assert m.stop_time_s(1.5) == pytest.approx(0.5)
    assert m.stop_time_s(0.3, 2.4) == pytest.approx(0.8)  # the joint limit rules
    assert m.stop_distance_m(1.5, 0.5) == pytest.approx(0.375)  # v^2 / 2a
    delayed = StoppingModel(delay_s=0.05)
    assert delayed.stop_time_s(1.5) == pytest.approx(0.55)
    assert delayed.stop_distance_m(1.5, 0.55) == pytest.approx(1.5 * 0.05 + 0.375)
    for bad in ({"decel_mps2": 0.0}, {"joint_decel_radps2": float("nan")}, {"delay_s": -0.1}):
        with pytest.raises(ValueError, match="StoppingModel"):
            StoppingModel(**bad)
    assert reaction_time_s(
        tracker_latency_s=0.06, frame_period_s=1 / 30, processing_s=0.01, servo_period_s=0.008
    ) == pytest.approx(0.1113, abs=1e-4)
    with pytest.raises(ValueError, match="tracker_latency_s"):
        reaction_time_s(tracker_latency_s=-1.0, frame_period_s=0.03, processing_s=0.0, servo_period_s=0.0)


def test_what_counts_as_an_intrusion() -> None:
    from app.safety.monitor import is_intrusion

    walking = np.full(NUM_JOINTS, 1.4)
    assert not is_intrusion(walking)
    swing = walking.copy()
    swing[[8, 12]] = 7.0  # both hands in a fast swing
    assert not is_intrusion(swing)
    glitch = walking.copy()
    glitch[12] = 18.0  # one joint jumps (a tracking or recording glitch)
    assert is_intrusion(glitch)
    assert is_intrusion(np.full(NUM_JOINTS, 6.0))  # the whole body moved 20 cm in a frame: someone else


def test_a_true_jump_starts_an_intrusion_whose_violation_is_counted_apart(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, 0.15)
    far = person + 0.8 * direction  # 0.8 m away 8 ms ago: someone appeared
    first = mon.check(0.0, q, qd, person, far, 0.008)
    assert first.violation
    assert mon.intrusions == 1 and mon.violations == 0 and mon.violations_in_intrusions == 1
    mon.check(0.008, q, np.zeros(6), person, person, 0.008)  # the robot at standstill: the episode ends
    # moving again inside S_p once T_r has passed (the system has seen the person): the planner's violation
    mon.check(0.016 + T_R, q, qd, person, person, 0.008)
    assert mon.violations == 1 and mon.violations_in_intrusions == 1


def test_a_violation_that_opens_within_the_reaction_time_of_a_jump_is_the_jumps(geometry) -> None:
    """An episode may open a check after the jump was seen: until ``T_r`` has passed no system can have
    reacted to it, so the episode is the intrusion's; after ``T_r`` it is the robot's."""
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, 0.15)
    far = person + 0.8 * direction
    # mid-jump, the robot still at rest (not judged): no episode yet
    mon.check(0.0, q, np.zeros(6), far, far + 0.15 * direction, 0.008)
    assert mon.intrusions == 1 and not mon.totals().episodes
    # the jump has landed inside S_p as the robot starts to move, on a decision from before the jump
    mon.check(0.008, q, qd, person, person, 0.008)
    assert mon.violations == 0 and mon.violations_in_intrusions == 1
    mon.check(0.016, q, np.zeros(6), person, person, 0.008)  # at standstill: the episode ends
    late = 0.016 + T_R + 0.01
    mon.check(late, q, qd, person, person, 0.008)  # moving again inside S_p after T_r: the robot's
    assert mon.violations == 1 and mon.violations_in_intrusions == 1


def test_every_episode_keeps_its_first_and_worst_check(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, 0.3)
    for k, gap in enumerate([0.6, 0.12, 0.08, 0.1, 0.6]):  # inside S_p for three checks, then recovered
        at = person + (gap - 0.3) * direction
        mon.check(0.008 * k, q, qd, at, at, 0.008)
    episodes = mon.totals().episodes
    kinds = [e.kind for e in episodes]
    assert kinds.count("violation") == 1
    ep = next(e for e in episodes if e.kind == "violation")
    assert not ep.intrusion
    assert ep.first.t == ep.start_s == pytest.approx(0.008)
    assert ep.first.separation_m == pytest.approx(0.12, abs=2e-3)
    assert ep.worst.t == pytest.approx(0.016) and ep.worst.separation_m == pytest.approx(0.08, abs=2e-3)
    assert ep.duration_s == pytest.approx(0.016)
    assert ep.to_json()["worst"]["part"] == ep.worst.part


def test_an_episode_still_under_way_when_the_trial_ends_is_listed(geometry) -> None:
    mon = _monitor(geometry)
    q, qd, person, direction = _scene(geometry, 0.3)
    at = person + (0.1 - 0.3) * direction
    mon.check(0.0, q, qd, at, at, 0.008)
    mon.check(0.008, q, qd, at, at, 0.008)
    episodes = mon.totals().episodes
    assert mon.violations == 1 and [e.kind for e in episodes].count("violation") == 1
    assert next(e for e in episodes if e.kind == "violation").duration_s == pytest.approx(0.008)
