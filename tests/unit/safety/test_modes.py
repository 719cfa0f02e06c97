"""What limits each robot part, as the operator sees it (:func:`app.safety.modes.part_modes`): a part near a
hand moving at the hand's permissible speed is ``pfl:hand_fingers``, a part far from everyone ``free``, a
part within ``S_p(0)`` of the head ``stopped``, a part slowed by its separation alone ``ssm``; the part that
limits the robot has the scale the governor's servo tick computes, and the separation it is held to is the
one the governor keeps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.planning.collision import HUMAN_CAPSULES
from app.safety._kernels import PartSeparation, RobotMotion, ServoGovernor, governed_scale
from app.safety.governor import BRAKE_INSTANTS, NO_LAW, SCALE_GRID, SeparationModel, ssm_alone
from app.safety.modes import (
    PART_MODES,
    REGION_LABELS,
    PartMode,
    RegionMap,
    binding_part,
    mode_text,
    part_modes,
    region_text,
)
from app.safety.pfl import BODY_REGIONS, PFLModel

# S_p = 0.11 + v_h (0.1 + T_s) + ..., the person at ISO 13855's constant speeds
MODEL = SeparationModel(
    s0_m=0.11, t_reaction_s=0.1, stop_decel_mps2=3.0, human_speed_max_mps=2.0, human_accel_mps2=0.0
)
GOVERNOR = ServoGovernor(MODEL.kernel_params, NO_LAW, SCALE_GRID, BRAKE_INSTANTS)
HAND = HUMAN_CAPSULES.index("l_wrist-l_hand")
HEAD = HUMAN_CAPSULES.index("head")
CHEST = HUMAN_CAPSULES.index("spine-chest")
RATE = 3.0  # a brake from full scale takes 1/3 s


def _scene(near: list[dict[int, float]], *, pfl: bool = True) -> tuple[PartSeparation, RegionMap, PFLModel]:
    """Robot parts (one per entry of ``near``) at the given distances from some of the person's capsules
    (every other capsule 3 m away), a still person approaching at ISO 13855's speeds."""
    model = PFLModel.for_capsules(HUMAN_CAPSULES, enabled=pfl)
    d = np.full((len(near), len(HUMAN_CAPSULES)), 3.0)
    for i, row in enumerate(near):
        for m, dist in row.items():
            d[i, m] = dist
    v = np.broadcast_to(model.iso_speeds_mps, d.shape)
    gaps = np.full(len(HUMAN_CAPSULES), 1.0)
    levels, caps = model.levels(d, v, gaps, band_m=0.25)
    near_band = d <= d.min(axis=1, keepdims=True) + 0.25
    v_h0 = np.where(near_band, v, 0.0).max(axis=1)
    parts = PartSeparation(d.min(axis=1), np.zeros(len(near)), v_h0, levels)
    regions = RegionMap(d, caps, model.regions)
    return parts, regions, model


def _motion(v_toward: list[float]) -> RobotMotion:
    v = np.asarray(v_toward, dtype=np.float64)
    return RobotMotion(np.abs(v), v, np.zeros(v.shape[0]))


def _modes(
    parts: PartSeparation, robot: RobotMotion, regions: RegionMap, **kw: object
) -> tuple[PartMode, ...]:
    args: dict[str, object] = dict(scale=1.0, dt_h=0.0, rate=RATE, regions=regions)
    args.update(kw)
    return part_modes(parts, robot, GOVERNOR, **args)  # type: ignore[arg-type]


def test_a_part_near_a_hand_at_the_hands_speed_is_pfl_hand_fingers() -> None:
    # a tool 3 cm from a hand, the head 1.5 m away, closing on the person at 2 m/s per unit scale
    parts, regions, _ = _scene([{HAND: 0.03, HEAD: 1.5}])
    (m,) = _modes(parts, _motion([2.0]), regions, scale=0.675)
    assert m.mode == "pfl" and m.region == "hand_fingers" and m.label == "pfl:hand_fingers"
    # the hand's permissible speed (1.36 m/s) caps it, on the governor's grid of 1/40
    assert m.limit_scale == pytest.approx(0.675) and m.v_toward_mps == pytest.approx(1.35)
    # it keeps S_p from the regions it may not touch at that speed: the head, 1.5 m away, the nearest of them
    assert m.held_from == "skull_forehead" and m.separation_m == pytest.approx(1.5)
    assert 0.11 < m.required_m < m.separation_m


def test_a_part_far_from_everyone_runs_free() -> None:
    parts, regions, _ = _scene([{HAND: 2.5, HEAD: 2.6}])
    (m,) = _modes(parts, _motion([1.0]), regions)
    assert m.mode == "free" and m.label == "free" and m.limit_scale == 1.0
    # at 1 m/s it may touch the hand (1.36 m/s) and keeps S_p from the slower regions: the head the nearest
    assert m.region == m.held_from == "skull_forehead"
    assert m.separation_m == pytest.approx(2.6) and m.margin_m > 1.0


def test_a_part_within_s_p_0_of_the_head_is_stopped() -> None:
    parts, regions, _ = _scene([{HEAD: 0.03, HAND: 1.0}])
    for v in (0.05, 1.0):
        (m,) = _modes(parts, _motion([v]), regions, scale=0.0)
        assert m.mode == "stopped" and m.label == "stopped" and m.limit_scale == 0.0
        assert m.region == m.held_from == "skull_forehead"
        # S_p(0) = C + Z_d + Z_r + v_h T_r = 0.11 + 1.6 * 0.1 from the head, which the part is well within
        assert m.required_m == pytest.approx(0.11 + 1.6 * 0.1)
        assert m.separation_m == pytest.approx(0.03) and m.margin_m < 0


def test_a_part_slowed_by_its_separation_alone_is_ssm_and_held_where_the_governor_holds_it() -> None:
    # SSM alone (PFL off): the chest at 0.8 m, closing at 1 m/s per unit scale
    parts, regions, _ = _scene([{CHEST: 0.8}], pfl=False)
    (m,) = _modes(parts, _motion([1.0]), regions, scale=1.0)
    assert m.mode == "ssm" and m.region == m.held_from == "chest"
    assert 0.0 < m.limit_scale < 1.0
    # at the scale it allows, the separation it is held to fits; one step of the grid faster, it does not
    (at,) = _modes(parts, _motion([1.0]), regions, scale=m.limit_scale)
    (over,) = _modes(parts, _motion([1.0]), regions, scale=m.limit_scale + 0.025)
    assert at.margin_m >= 0.0 > over.margin_m


def test_a_robot_held_by_the_supervisor_is_stopped_everywhere_and_a_still_robot_is_not_slowed() -> None:
    parts, regions, _ = _scene([{HAND: 2.5}, {HAND: 0.03, HEAD: 1.5}])
    held = _modes(parts, _motion([1.0, 2.0]), regions, held=True, scale=0.0)
    assert [m.mode for m in held] == ["stopped", "stopped"] and all(m.limit_scale == 0.0 for m in held)
    still = _modes(parts, _motion([0.0, 0.0]), regions, scale=0.0)
    assert [m.mode for m in still] == ["free", "free"]
    # without a region map (no person model) the modes stand, the regions are not named
    bare = part_modes(parts, _motion([1.0, 2.0]), GOVERNOR, scale=0.675, dt_h=0.0, rate=RATE)
    assert [m.mode for m in bare] == ["free", "pfl"] and all(m.region is None for m in bare)


def test_nobody_seen_every_part_runs_free_with_no_region() -> None:
    n = 2
    # the supervisor's state before its first frame
    parts = PartSeparation(np.full(n, math.inf), np.zeros(n), np.zeros(n), ssm_alone(n))
    modes = part_modes(parts, _motion([1.0, 0.5]), GOVERNOR, scale=1.0, dt_h=math.nan, rate=RATE)
    assert [m.mode for m in modes] == ["free", "free"]
    assert all(m.region is None and m.margin_m == math.inf for m in modes)


@pytest.mark.parametrize("seed", range(8))
def test_the_limiting_part_has_the_scale_of_the_servo_tick(seed: int) -> None:
    """The smallest of the parts' own scales is the governor's answer over all of them (same inputs, a
    tick of no length), so the mode shown is the one that holds the robot."""
    rng = np.random.default_rng(seed)
    near = [
        {
            HAND: float(rng.uniform(0.0, 1.2)),
            HEAD: float(rng.uniform(0.1, 1.5)),
            CHEST: float(rng.uniform(0.2, 2)),
        }
        for _ in range(5)
    ]
    parts, regions, _ = _scene(near)
    robot = _motion(list(rng.uniform(-0.5, 2.0, 5)))
    dt_h = float(rng.uniform(0.0, 0.1))
    modes = part_modes(parts, robot, GOVERNOR, scale=0.5, dt_h=dt_h, rate=RATE, regions=regions)
    assert all(m.mode in PART_MODES for m in modes)
    tick = governed_scale(parts, robot, dt_h, 0.5, 0.0, RATE, 0.0, 1.0, GOVERNOR)
    # (a part within S_p(0) of the head is stopped by the supervisor's rule, whatever the governor allows)
    stop_rule = any(m.mode == "stopped" and m.held_from == "skull_forehead" for m in modes)
    assert modes[binding_part(modes)].limit_scale == pytest.approx(0.0 if stop_rule else tick)
    assert binding_part(()) == -1


def test_the_screens_name_every_mode_and_every_region() -> None:
    assert set(REGION_LABELS) == set(BODY_REGIONS)
    assert mode_text("free") == "free" and mode_text("ssm") == "SSM" and mode_text("stopped") == "stopped"
    assert mode_text("pfl:hand_fingers") == "PFL · hand/fingers" and mode_text(None) == "–"
    assert region_text("upper_arm_elbow") == "upper arm/elbow"


def test_crossing_a_far_regions_speed_is_not_pfl() -> None:
    """Faster than the lower leg's permissible speed (0.36 m/s), a part must keep S_p from the legs too, but
    they are 3 m away: what holds it near the head is its S_p from the head (SSM), not the legs' speed."""
    parts, regions, _ = _scene([{HEAD: 0.55}])
    (m,) = _modes(parts, _motion([1.5]), regions, scale=0.3)
    assert 0.36 < m.limit_scale * 1.5 < 1.36  # between the legs' and the hand's speeds
    assert m.mode == "ssm" and m.region == m.held_from == "skull_forehead"
