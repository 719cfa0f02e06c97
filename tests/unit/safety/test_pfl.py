"""Power and force limiting inside S_p and ISO 13855's person: the Annex A speeds against a hand computation,
the governor's combined rule (a hand's speed near a hand, a stop near a head, the quasi-static speed where a
hand lies on the table, a part moving away not slowed) and a person never assumed slower than ISO 13855's."""

from __future__ import annotations

import math

import numpy as np
import pytest
from governor_reference import pfl_levels_reference

from app.config import Settings, load_workcell
from app.control.engine import approach_floors, pfl_model
from app.control.stack import CellGeometry
from app.planning.collision import HUMAN_CAPSULES, CollisionModel
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS
from app.safety.governor import SeparationModel, directed_pairs
from app.safety.pfl import (
    BODY_REGIONS,
    UR5E_MOVING_MASS_KG,
    PFLModel,
    capsule_region,
    permissible_speed_mps,
    pfl_levels,
)

# S_p = 0.11 + v_h (0.1 + T_s) + ..., the person at ISO 13855's constant 2.0 m/s
MODEL = SeparationModel(
    s0_m=0.11, t_reaction_s=0.1, stop_decel_mps2=3.0, human_speed_max_mps=2.0, human_accel_mps2=0.0
)
HAND = HUMAN_CAPSULES.index("l_wrist-l_hand")
HEAD = HUMAN_CAPSULES.index("head")


def test_the_annex_a_speeds_match_a_hand_computation() -> None:
    """v = F / sqrt(mu k), mu = (1/m_H + 1/m_R)^-1, m_R = M/2 + m_L: the UR5e's 17.7 kg of moving links
    (3.761 + 8.058 + 2.846 + 1.370 + 1.300 + 0.365) and 1 kg of gripper and part."""
    assert pytest.approx(17.7, abs=1e-9) == UR5E_MOVING_MASS_KG
    m_r = 17.7 / 2 + 1.0  # 9.85 kg
    by_hand = {
        # region: (2 x Table A.2's force N, k N/m, m_H kg)
        "hand_fingers": (280.0, 75e3, 0.6),
        "lower_arm_wrist": (320.0, 40e3, 2.0),
        "upper_arm_elbow": (300.0, 30e3, 3.0),
        "chest": (280.0, 25e3, 40.0),
        "abdomen": (220.0, 10e3, 40.0),
    }
    for name, (f, k, m_h) in by_hand.items():
        mu = 1.0 / (1.0 / m_h + 1.0 / m_r)
        want = f / math.sqrt(mu * k)
        got = permissible_speed_mps(BODY_REGIONS[name], robot_mass_kg=17.7, payload_kg=1.0)
        assert got == pytest.approx(want, rel=1e-12), name
        quasi = permissible_speed_mps(
            BODY_REGIONS[name], robot_mass_kg=17.7, payload_kg=1.0, quasi_static=True
        )
        assert quasi == pytest.approx(want / 2, rel=1e-12), name
    # the rough figures: hands and arms 1.1-1.4 m/s, chest and abdomen 0.6-0.8 m/s
    assert (
        1.35 < permissible_speed_mps(BODY_REGIONS["hand_fingers"], robot_mass_kg=17.7, payload_kg=1.0) < 1.37
    )
    assert 0.62 < permissible_speed_mps(BODY_REGIONS["chest"], robot_mass_kg=17.7, payload_kg=1.0) < 0.64
    for name in ("skull_forehead", "face", "neck"):
        assert permissible_speed_mps(BODY_REGIONS[name], robot_mass_kg=17.7, payload_kg=1.0) == 0.0


def test_every_capsule_of_the_person_has_a_region_and_iso_13855_speed() -> None:
    model = PFLModel.for_capsules(HUMAN_CAPSULES)
    regions = dict(zip(HUMAN_CAPSULES, model.regions, strict=True))
    assert regions["head"] == "skull_forehead" and regions["neck-head"] == "neck"
    assert regions["l_wrist-l_hand"] == "hand_fingers" and regions["r_elbow-r_wrist"] == "lower_arm_wrist"
    assert regions["spine-chest"] == "chest" and regions["pelvis-spine"] == "abdomen"
    speeds = dict(zip(HUMAN_CAPSULES, model.iso_speeds_mps, strict=True))
    assert speeds["l_wrist-l_hand"] == 2.0 and speeds["r_shoulder-r_elbow"] == 2.0
    assert speeds["head"] == 1.6 and speeds["spine-chest"] == 1.6
    caps = dict(zip(HUMAN_CAPSULES, model.transient_mps, strict=True))
    assert caps["head"] < 0 and caps["neck-head"] < 0 and caps["l_wrist-l_hand"] > 1.3
    assert np.all(PFLModel.for_capsules(HUMAN_CAPSULES, enabled=False).transient_mps < 0)
    with pytest.raises(ValueError, match="no body region"):
        capsule_region("tail-tip")


def _levels(d_hand: float, d_head: float, *, pinned: bool = False):
    """One robot part at ``d_hand`` from a hand and ``d_head`` from the head (every other capsule 3 m away),
    the person approaching at ISO 13855's speeds."""
    model = PFLModel.for_capsules(HUMAN_CAPSULES)
    d = np.full((1, len(HUMAN_CAPSULES)), 3.0)
    d[0, HAND], d[0, HEAD] = d_hand, d_head
    v = np.broadcast_to(model.iso_speeds_mps, d.shape)
    gaps = np.full(len(HUMAN_CAPSULES), 1.0)
    if pinned:
        gaps[HAND] = 0.0
    return model.levels(d, v, gaps, band_m=0.25)[0], float(d.min())


def test_a_part_approaching_a_hand_is_allowed_the_hands_speed_and_one_approaching_a_head_is_stopped() -> None:
    lv, sep = _levels(0.03, 1.5)  # a hand 3 cm from the tool, the head 1.5 m away
    kw = dict(v_human_mps=np.array([2.0]), rate=3.0)
    # SSM alone: within S_p(0) of the hand, no motion at all
    assert MODEL.max_scale(np.array([sep]), v_parts_mps=np.array([1.0]), **kw) == 0.0
    # with PFL: toward the hand at 1.0 m/s per unit scale, up to the hand's 1.36 m/s (the whole scale here)
    assert MODEL.max_scale(np.array([sep]), v_parts_mps=np.array([1.0]), pfl=lv, **kw) == 1.0
    # at 2.0 m/s per unit scale: the hand's speed caps it (1.36 / 2, on the governor's grid of 1/40)
    s = MODEL.max_scale(np.array([sep]), v_parts_mps=np.array([2.0]), pfl=lv, **kw)
    assert s * 2.0 <= 1.36 and s == pytest.approx(0.675)
    # the head within S_p(0): stopped, whatever the speed
    lv_head, sep_head = _levels(1.5, 0.03)
    for v in (0.05, 1.0):
        assert MODEL.max_scale(np.array([sep_head]), v_parts_mps=np.array([v]), pfl=lv_head, **kw) == 0.0


def test_a_tool_coming_down_on_a_hand_on_the_table_gets_the_quasi_static_speed() -> None:
    """A hand lying on the table under the tool could be pinned there: Table A.2's force without the factor
    2, half the transient speed."""
    geometry = CellGeometry(CollisionModel(load_workcell()))
    joints = np.zeros((NUM_JOINTS, 3)) + np.array([1.3, 0.0, 1.0])
    joints[JOINT_INDEX["l_wrist"]] = [0.55, 0.0, 0.06]  # on the table top (z = 0), under a drop station
    joints[JOINT_INDEX["l_hand"]] = [0.55, 0.1, 0.06]
    gaps = geometry.human_static_gaps(joints)
    assert gaps[HAND] <= 0.01 and gaps[HUMAN_CAPSULES.index("spine-chest")] > 0.3
    lv, sep = _levels(0.03, 1.5, pinned=True)
    kw = dict(v_human_mps=np.array([2.0]), rate=3.0)
    s = MODEL.max_scale(np.array([sep]), v_parts_mps=np.array([1.0]), pfl=lv, **kw)
    quasi = PFLModel.for_capsules(HUMAN_CAPSULES).quasi_static_mps[HAND]
    assert quasi == pytest.approx(0.68, abs=0.01)
    assert s <= quasi and s == pytest.approx(0.675)


def test_a_part_moving_away_is_not_slowed() -> None:
    lv, sep = _levels(0.03, 1.5)
    kw = dict(v_human_mps=np.array([2.0]), rate=3.0)
    # moving away from the hand at 1 m/s per unit scale: full scale (it could touch nothing faster than that)
    assert MODEL.max_scale(np.array([sep]), v_parts_mps=np.array([-1.0]), pfl=lv, **kw) == 1.0
    # and a part far from everyone runs free
    assert (
        MODEL.max_scale(np.array([2.5]), v_parts_mps=np.array([1.0]), pfl=_levels(2.5, 2.6)[0], **kw) == 1.0
    )


def test_the_governor_never_assumes_a_person_slower_than_iso_13855() -> None:
    geometry = CellGeometry(CollisionModel(load_workcell()))
    q = np.asarray(load_workcell().robot.home_q, dtype=float)
    person = np.zeros((NUM_JOINTS, 3)) + np.array([1.2, 0.0, 0.6]) + np.linspace(0, 0.3, NUM_JOINTS)[:, None]
    floors = approach_floors(Settings())
    assert np.all(floors >= 1.6) and floors[HAND] == 2.0 and floors[HEAD] == 1.6
    # a still person, measured: ISO 13855's speeds; a faster one: the measured speed
    _, v_still = directed_pairs(geometry, q, person, person, 0.1, v_unknown_mps=2.0, floor_mps=floors)
    assert np.all(v_still >= floors[None, :])
    toward = person - 0.3 * (person - np.array([0.3, 0.0, 0.4])) / np.linalg.norm(
        person - np.array([0.3, 0.0, 0.4]), axis=1, keepdims=True
    )  # 0.3 m toward the robot in 0.1 s: about 3 m/s
    _, v_fast = directed_pairs(geometry, q, toward, person, 0.1, v_unknown_mps=2.0, floor_mps=floors)
    assert v_fast.max() > 2.5
    # the settings refuse a slower person for ISO 13855's model (the what-if model may set its own)
    with pytest.raises(ValueError, match="below ISO 13855"):
        Settings(human_speed_max_mps=1.5)
    assert Settings(human_model="cmu_p99").assumed_human_speed_mps == 3.65
    assert Settings().assumed_human_speed_mps == 2.0 and Settings().assumed_human_accel_mps2 == 0.0
    assert approach_floors(Settings(human_model="cmu_p99")) is None  # the measured speed alone
    assert pfl_model(Settings(pfl=False)).enabled is False


def test_the_levels_keep_s_p_from_the_regions_a_part_would_touch_too_fast() -> None:
    caps = np.array([-1.0, 0.6, 1.3])  # a head, a chest, a hand
    d = np.array([[0.9, 0.5, 0.1], [0.2, 0.4, 0.6]])
    v = np.array([[1.6, 1.6, 2.0], [1.6, 1.6, 2.0]])
    levels, extra, v_h = pfl_levels(d, caps, v, band_m=0.05)
    assert levels.tolist() == [-1.0, 0.6, 1.3]
    # part 0: the head 0.8 m beyond its nearest (the hand), the chest 0.4, all 0
    assert extra[0].tolist() == pytest.approx([0.8, 0.4, 0.0])
    assert extra[1].tolist() == pytest.approx([0.0, 0.0, 0.0])  # its nearest is the head
    assert v_h[0].tolist() == [1.6, 1.6, 2.0]
    _, _, no_v = pfl_levels(d, caps)
    assert np.all(np.isinf(no_v))


@pytest.mark.parametrize("seed", range(5))
def test_the_compiled_pfl_levels_match_their_numpy_form(seed: int) -> None:
    """Random separations of 7 parts to 1-4 stacked bodies, with and without the approach speeds, some
    capsules of no permitted contact."""
    rng = np.random.default_rng(seed)
    m = len(HUMAN_CAPSULES) * int(rng.integers(1, 5))
    d = rng.uniform(-0.05, 2.0, size=(7, m))
    caps = rng.choice([-1.0, 0.6, 0.75, 1.3, 1.4], size=m)
    v = rng.uniform(-1.0, 3.0, size=(7, m))
    for v_pairs in (v, None):
        got = pfl_levels(d, caps, v_pairs, band_m=0.1)
        want = pfl_levels_reference(d, caps, v_pairs, band_m=0.1)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
