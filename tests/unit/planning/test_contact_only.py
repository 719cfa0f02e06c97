"""The planner's compiled checks with contact clearance for the body regions that admit contact
(``PlannerConfig.contact_only``): a forecast hand next to the robot is no obstacle, only touching it is; a
forecast head keeps the whole clearance; and without the flags every region keeps it (SSM alone)."""

from __future__ import annotations

import numpy as np
import pytest

from app.config import Settings, load_workcell
from app.control.stack import PlanningStack, contact_only_capsules
from app.planning.collision import HUMAN_CAPSULES
from app.planning.search import Planner, PlannerConfig
from app.planning.trajectory import Trajectory
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, HumanFrame
from app.safety.pfl import capsule_region
from app.safety.ssm import forecast_clearance

NO_CONTACT = {"skull_forehead", "face", "neck"}


@pytest.fixture(scope="module")
def stack() -> PlanningStack:
    return PlanningStack.for_cell(load_workcell())


@pytest.fixture(scope="module")
def flags() -> tuple[bool, ...]:
    return tuple(capsule_region(c) not in NO_CONTACT for c in HUMAN_CAPSULES)


def _planner(stack: PlanningStack, contact_only: tuple[bool, ...], *, search: bool = True) -> Planner:
    config = PlannerConfig(contact_only=contact_only, contact_only_search=search)
    return Planner(stack.roadmap, stack.collision, config=config)


def _at_rest(q: np.ndarray) -> Trajectory:
    return Trajectory(np.array([0.0, 1.0]), np.stack([q, q]), np.zeros((2, 6)))


def _person_with(stack: PlanningStack, q: np.ndarray, joint: str, gap_m: float) -> HumanForecast:
    """A person far from the robot but for one joint, placed straight below the tool capsule's round end so
    that the capsules ending there are ``gap_m`` (surface to surface) from the robot at ``q``."""
    joints = np.full((NUM_JOINTS, 3), 6.0) + np.linspace(0.0, 0.3, NUM_JOINTS)[:, None]
    tip = stack.collision.robot_capsules(q[None])[1][0, -1]  # the tool capsule's round end (downward)
    joints[JOINT_INDEX[joint]] = tip
    # lowered below the tip by bisection on the real distance (the capsules' radii and directions included)
    lo, hi = tip[2] - 1.0, tip[2]
    d = np.nan
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        joints[JOINT_INDEX[joint], 2] = mid
        d = float(stack.collision.distance_to_human_paired(q[None], joints[None])[0])
        lo, hi = (mid, hi) if d > gap_m else (lo, mid)
    assert abs(d - gap_m) < 1e-4
    return HumanForecast.hold(HumanFrame(0.0, joints))


def test_the_product_asks_contact_only_of_the_regions_that_admit_contact_and_only_with_pfl() -> None:
    on = contact_only_capsules(Settings(pfl=True, plan_contact_regions="checks"))
    assert len(on) == len(HUMAN_CAPSULES)
    for name, soft in zip(HUMAN_CAPSULES, on, strict=True):
        assert soft == (capsule_region(name) not in NO_CONTACT), name
    assert contact_only_capsules(Settings(pfl=True, plan_contact_regions="all")) == on
    assert contact_only_capsules(Settings(pfl=False, plan_contact_regions="all")) == ()
    assert contact_only_capsules(Settings(pfl=True, plan_contact_regions="none")) == ()


def test_a_forecast_hand_next_to_the_robot_blocks_it_only_without_contact_clearance(stack, flags) -> None:  # type: ignore[no-untyped-def]
    q = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    ssm = stack.planner.config.ssm
    full = float(forecast_clearance(0.0, 0.0, ssm, w_top_radps=0.0))
    soft = ssm.z_human_m
    assert full - soft > 0.05  # the scene tells the two requirements apart
    gap = 0.5 * (soft + full)
    hand = _person_with(stack, q, "r_hand", gap)
    traj = _at_rest(q)
    strict, lax = _planner(stack, ()), _planner(stack, flags)
    assert strict.first_violation(traj, hand, t_from=0.0, t_to=1.0) is not None
    assert lax.first_violation(traj, hand, t_from=0.0, t_to=1.0) is None
    # touching the hand (closer than Z_d, the sensing uncertainty) is refused with contact clearance too
    touching = _person_with(stack, q, "r_hand", 0.5 * soft)
    assert lax.first_violation(traj, touching, t_from=0.0, t_to=1.0) is not None


def test_a_forecast_head_next_to_the_robot_keeps_the_whole_clearance(stack, flags) -> None:  # type: ignore[no-untyped-def]
    q = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    ssm = stack.planner.config.ssm
    full = float(forecast_clearance(0.0, 0.0, ssm, w_top_radps=0.0))
    head = _person_with(stack, q, "head", 0.5 * (ssm.z_human_m + full))
    traj = _at_rest(q)
    for planner in (_planner(stack, ()), _planner(stack, flags)):
        assert planner.first_violation(traj, head, t_from=0.0, t_to=1.0) is not None
    # and beyond the whole clearance both accept it
    clear = _person_with(stack, q, "head", full + 0.02)
    for planner in (_planner(stack, ()), _planner(stack, flags)):
        assert planner.first_violation(traj, clear, t_from=0.0, t_to=1.0) is None


def test_the_search_plans_past_a_forecast_hand_only_with_contact_clearance(stack, flags) -> None:  # type: ignore[no-untyped-def]
    """A hand held at the goal's approach pose: the strict search cannot end there, the one with contact
    clearance can (the goal itself is not touched)."""
    goal = "B_approach"
    node = stack.roadmap.station_nodes[goal]
    q_goal = stack.roadmap.ik[node][stack.roadmap.valid[node]][0]
    full = float(forecast_clearance(0.0, 0.0, stack.planner.config.ssm, w_top_radps=0.0))
    soft = stack.planner.config.ssm.z_human_m
    hand = _person_with(stack, q_goal, "r_hand", soft + 0.6 * (full - soft))
    q0 = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    strict = _planner(stack, ()).plan(q_start=q0, t_start=0.0, goal=goal, forecast=hand)
    lax = _planner(stack, flags).plan(q_start=q0, t_start=0.0, goal=goal, forecast=hand)
    assert not strict.ok
    assert lax.ok, lax.reason
    # with contact clearance in the trajectory checks alone, the search stays as strict, and its plans pass
    checks_only = _planner(stack, flags, search=False)
    assert not checks_only.plan(q_start=q0, t_start=0.0, goal=goal, forecast=hand).ok
    t_end = lax.trajectory.t_end
    assert checks_only.first_violation(lax.trajectory, hand, t_from=0.0, t_to=t_end) is None
    assert _planner(stack, ()).first_violation(lax.trajectory, hand, t_from=0.0, t_to=t_end) is not None


def test_contact_flags_of_the_wrong_length_are_refused_and_equal_flags_share_a_geometry(stack, flags) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match="one flag per person capsule"):
        stack.collision.kernel_geometry_for(1, (True, False))
    geo = stack.collision.kernel_geometry_for
    assert geo(2, flags) is geo(2, tuple(flags))
    none = (False,) * len(HUMAN_CAPSULES)
    assert geo(1, none) is geo(1)


def test_the_planning_benchs_independent_check_asks_of_each_region_what_the_checks_ask(stack, flags) -> None:  # type: ignore[no-untyped-def]
    from app.bench.planning import count_violations

    q = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    ssm, stopping = stack.planner.config.ssm, stack.planner.config.stopping
    gap = 0.5 * (ssm.z_human_m + float(forecast_clearance(0.0, 0.0, ssm, w_top_radps=0.0)))
    hold = _at_rest(q)
    hand = _person_with(stack, q, "r_hand", gap)  # inside the whole clearance, beyond Z_d
    kw = {"hold_s": 0.0, "stopping": stopping}
    assert count_violations(hold, hand, stack.collision, ssm, **kw) == 1
    assert count_violations(hold, hand, stack.collision, ssm, contact_only=flags, **kw) == 0
    head = _person_with(stack, q, "head", gap)  # a head keeps the whole clearance either way
    assert count_violations(hold, head, stack.collision, ssm, contact_only=flags, **kw) == 1
    touching = _person_with(stack, q, "r_hand", 0.5 * ssm.z_human_m)
    assert count_violations(hold, touching, stack.collision, ssm, contact_only=flags, **kw) == 1


def test_the_planner_and_the_benchs_check_keep_the_cells_joint_limits(stack) -> None:  # type: ignore[no-untyped-def]
    from app.bench.planning import count_violations

    lo, hi = stack.cell.robot.joint_limits()
    np.testing.assert_array_equal(stack.planner.q_min, lo)
    np.testing.assert_array_equal(stack.planner.q_max, hi)
    assert hi[4] == 0.0  # the shipped cell's wrist 2
    q = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    q[4] = np.pi / 2  # the wrist flipped: within the UR5e's limits, outside the cell's
    far = HumanForecast.hold(HumanFrame(0.0, np.full((NUM_JOINTS, 3), 6.0)))
    ssm, kw = stack.planner.config.ssm, {"hold_s": 0.0, "stopping": stack.planner.config.stopping}
    assert count_violations(_at_rest(q), far, stack.collision, ssm, **kw) == 0
    assert count_violations(_at_rest(q), far, stack.collision, ssm, limits=(lo, hi), **kw) == 1


def _speeds(flags: tuple[bool, ...]) -> tuple[float, ...]:
    """Each contact-only capsule's permissible quasi-static speed, as the product sets them."""
    from app.control.stack import contact_clearance

    speeds = contact_clearance(Settings())["contact_speed_mps"]
    assert len(speeds) == len(flags)
    return speeds


def test_the_product_lets_the_checks_accept_a_contact_only_below_each_regions_quasi_static_speed(
    flags,
) -> None:  # type: ignore[no-untyped-def]
    from app.control.stack import contact_clearance, pfl_model

    speeds = _speeds(flags)
    quasi = pfl_model(Settings()).quasi_static_mps
    for name, soft, v, q in zip(HUMAN_CAPSULES, flags, speeds, quasi, strict=True):
        assert v == (q if soft else -1.0), name
    hand = HUMAN_CAPSULES.index("r_wrist-r_hand")
    assert speeds[hand] == pytest.approx(0.68, abs=0.01)  # half the hand's transient 1.36 m/s
    assert contact_clearance(Settings(plan_contact_speed=False))["contact_speed_mps"] == ()
    assert contact_clearance(Settings(pfl=False))["contact_speed_mps"] == ()
    with pytest.raises(ValueError, match="one speed per capsule"):
        PlannerConfig(contact_only=flags, contact_speed_mps=(0.5,))


def test_a_robot_slower_than_the_regions_contact_speed_may_touch_a_forecast_hand_a_faster_one_not(
    stack, flags
) -> None:  # type: ignore[no-untyped-def]
    """At rest (or creeping) beside a hand that may touch it, the robot is no danger to it: a contact stays
    within the hand's permissible quasi-static speed. Turning the base fast past the same hand, it is
    refused; a head keeps the whole clearance whatever the speed."""
    speeds = _speeds(flags)
    q = np.asarray(stack.cell.robot.home_q, dtype=np.float64)
    ssm = stack.planner.config.ssm
    touching = _person_with(stack, q, "r_hand", 0.5 * ssm.z_human_m)
    config = PlannerConfig(contact_only=flags, contact_speed_mps=speeds)
    free = Planner(stack.roadmap, stack.collision, config=config)
    assert _planner(stack, flags).first_violation(_at_rest(q), touching, t_from=0.0, t_to=1.0) is not None
    assert free.first_violation(_at_rest(q), touching, t_from=0.0, t_to=1.0) is None
    dq = np.array([2.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # the base at 2 rad/s: the tool well above 0.68 m/s
    turn = Trajectory(np.array([0.0, 0.2]), np.stack([q, q + 0.2 * dq]), np.stack([dq, dq]))
    assert float(stack.geometry.part_speeds(q, dq).max()) > 0.68
    assert free.first_violation(turn, touching, t_from=0.0, t_to=0.2) is not None
    full = float(forecast_clearance(0.0, 0.0, ssm, w_top_radps=0.0))
    head = _person_with(stack, q, "head", 0.5 * (ssm.z_human_m + full))
    assert free.first_violation(_at_rest(q), head, t_from=0.0, t_to=1.0) is not None
    # the bench's independent check asks the same
    from app.bench.planning import count_violations

    kw = {"hold_s": 0.0, "stopping": stack.planner.config.stopping, "contact_only": flags}
    assert count_violations(_at_rest(q), touching, stack.collision, ssm, **kw) == 1
    assert count_violations(_at_rest(q), touching, stack.collision, ssm, contact_speed_mps=speeds, **kw) == 0
    assert count_violations(turn, touching, stack.collision, ssm, contact_speed_mps=speeds, **kw) == 1
    assert count_violations(_at_rest(q), head, stack.collision, ssm, contact_speed_mps=speeds, **kw) == 1
