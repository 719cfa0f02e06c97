"""Every person of a scenario in the simulated cell: walkers walk like people, pass the robot as the
scenario says and come and go from the frames; a second operator fetches their stations' blocks; the same
seeds give the same people; the tracker model keeps each body's id."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from app.cell.operator_sim import OperatorParams, SimulatedOperator
from app.cell.people_sim import (
    FIRST_WALKER_ID,
    OPERATOR_ID,
    SECOND_OPERATOR_ID,
    PeopleOracle,
    SimulatedPeople,
    Walker,
)
from app.cell.scenario import PassersBy, Scenario, ScenarioError, load_scenario
from app.cell.tracker import TrackedSource, TrackerModel
from app.cell.validation import CellVolume
from app.config import load_workcell
from app.prediction.skeleton import JOINT_INDEX, NUM_JOINTS, bone_lengths

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"
FPS = 30.0


@functools.cache
def _cell():  # type: ignore[no-untyped-def]
    return load_workcell()


def _people(scenario: Scenario | str, *, seed: int = 5, participant_seed: int = 3) -> SimulatedPeople:
    cell = _cell()
    if isinstance(scenario, str):
        scenario = load_scenario(EXAMPLES / scenario)
    op = SimulatedOperator(cell, OperatorParams.draw(participant_seed), seed=seed, noise=False)
    return SimulatedPeople.from_scenario(cell, scenario, op, seed=seed, participant_seed=participant_seed)


def _walker(speed: tuple[float, float] = (1.0, 1.5), enter: str = "left", seed: int = 2) -> Walker:
    spec = PassersBy(interval_s=[20.0, 40.0], speed_mps=list(speed), enter_from=[enter], curve_m=[0.0, 0.15])
    return Walker(_cell(), spec, OperatorParams.draw(seed), seed=seed)


@pytest.mark.parametrize("enter", ["left", "right", "back", "front"])
def test_a_walker_walks_like_a_person(enter: str) -> None:
    w = _walker(enter=enter, seed=len(enter))
    w.passes_until(60.0)
    p = w.passes[0]
    ts = np.arange(p.t_start, p.t_end, 1 / FPS)
    poses = np.array([w.walking_pose(float(t)) for t in ts])
    assert poses.shape == (ts.size, NUM_JOINTS, 3)
    # bones keep their length
    bones = bone_lengths(poses)
    assert np.max(np.ptp(bones, axis=0)) < 1e-9
    floor = _cell().operator.floor_z
    height = w.params.height_m
    ankles = poses[:, [JOINT_INDEX["l_ankle"], JOINT_INDEX["r_ankle"]], :]
    lowest = ankles[:, :, 2].min(axis=1) - floor
    ankle_z = w.body.ankle_z
    # a foot is always on the floor (its heel up by a centimetre at most), the swing foot lifts < 20 cm
    assert np.all(lowest >= ankle_z - 1e-9) and np.all(lowest < ankle_z + 0.01)
    assert np.mean(lowest < ankle_z + 1e-9) > 0.8
    assert 0.08 < ankles[:, :, 2].max() - floor - ankle_z < 0.2
    # a planted foot does not slide (less than a millimetre a frame where a bowed path turns the body)
    for a in range(2):
        planted = (ankles[:-1, a, 2] - floor < ankle_z + 1e-9) & (ankles[1:, a, 2] - floor < ankle_z + 1e-9)
        slide = np.linalg.norm(np.diff(ankles[:, a, :2], axis=0), axis=1)[planted]
        assert planted.any() and slide.max() < 1e-3
    # the knees flex (forward) by less than 30 degrees while the foot is planted
    for hip, knee, ankle in ((13, 14, 15), (16, 17, 18)):
        thigh, shank = poses[:, knee] - poses[:, hip], poses[:, ankle] - poses[:, knee]
        cos = np.sum(thigh * shank, axis=1) / np.linalg.norm(thigh, axis=1) / np.linalg.norm(shank, axis=1)
        flexion = np.degrees(np.arccos(np.clip(cos, -1, 1)))
        down = poses[:, ankle, 2] - floor < ankle_z + 1e-9
        assert flexion[down].max() < 30.0 and flexion.max() < 75.0
    # the head at standing height, the pelvis a leg's length up, bobbing a few centimetres
    head = poses[:, JOINT_INDEX["head"], 2] - floor
    assert np.all((head > 0.8 * height) & (head < height))
    pelvis_z = poses[:, 0, 2] - floor
    assert 0.02 < np.ptp(pelvis_z) < 0.06
    # the speed of the pass, in the scenario's range
    v = np.linalg.norm(np.diff(poses[:, 0, :2], axis=0), axis=1) * FPS
    assert 1.0 <= p.speed_mps <= 1.5
    assert np.median(v) == pytest.approx(p.speed_mps, rel=0.02)
    # the hands swing, in turn
    lh = poses[:, JOINT_INDEX["l_hand"]] - poses[:, 0]
    assert np.ptp(lh @ np.array([*np.diff(p.point([0.0, 1.0]), axis=0)[0], 0.0])) > 0.1


def test_with_a_passer_by_the_frames_hold_two_bodies_while_they_are_in_the_cell() -> None:
    people = _people("scenario_passer_by.toml")
    walker = people.walkers[FIRST_WALKER_ID]
    ts = np.arange(0.0, 150.0, 1 / FPS)
    ids = [people.body_ids_at(float(t)) for t in ts]
    present = np.array([walker.pose_at(float(t)) is not None for t in ts])
    expected = [(OPERATOR_ID, FIRST_WALKER_ID) if p else (OPERATOR_ID,) for p in present]
    assert ids == expected
    for t in ts[::7]:
        f = people.true_frame(float(t))
        assert f is not None and f.joints.shape == (f.bodies * NUM_JOINTS, 3)
        assert np.array_equal(f.joints, people.pose_at(float(t)))
    # the walker comes and goes: several passes, each a few seconds in the cell
    entries = np.flatnonzero(np.diff(present.astype(int)) == 1)
    assert len(entries) >= 3
    assert 0.05 < present.mean() < 0.5


def test_passes_come_within_half_a_metre_of_the_reach_at_the_drawn_interval() -> None:
    people = _people("scenario_passer_by.toml", seed=11)
    walker = people.walkers[FIRST_WALKER_ID]
    spec = walker.spec
    passes = walker.passes_until(600.0)[:-1]
    assert len(passes) >= 12
    gaps = np.diff([p.t_closest for p in passes])
    assert np.all((gaps >= 20.0 - 1e-9) & (gaps <= 40.0 + 1e-9))
    assert {p.enter_from for p in passes} == {"left", "right", "back", "front"}
    base = np.asarray(_cell().robot.base_xyz[:2])
    for p in passes:
        ts = np.arange(p.t_start, p.t_end, 1 / FPS)
        poses = np.array([walker.walking_pose(float(t)) for t in ts])
        pelvis = np.linalg.norm(poses[:, 0, :2] - base, axis=1)
        nearest = np.linalg.norm(poses[:, :, :2] - base, axis=2).min()
        i = int(np.argmin(pelvis))
        assert pelvis[i] - spec.reach_m == pytest.approx(p.clearance_m, abs=0.01)
        assert 0.2 - 0.01 <= pelvis[i] - spec.reach_m <= 0.5 + 0.01
        assert ts[i] == pytest.approx(p.t_closest, abs=2 / FPS)
        assert nearest - spec.reach_m < 0.5
        # they are in the cell (the frames) at their closest approach
        assert walker.pose_at(p.t_closest) is not None


def test_a_path_through_the_table_is_refused() -> None:
    near = Scenario.model_validate({"passers_by": {"clearance_m": [0.0, 0.1], "enter_from": ["back"]}})
    with pytest.raises(ScenarioError, match=r"comes within .* of table"):
        _people(near)


def test_the_second_operator_fetches_the_blocks_of_their_stations() -> None:
    people = _people("scenario_second_operator.toml")
    second = people.operators[SECOND_OPERATOR_ID]
    assert people.station_owner == {"A": OPERATOR_ID, "B": OPERATOR_ID, "C": OPERATOR_ID, "D": 1}
    assert [s.name for s in second.cell.drop_stations] == ["D"]
    # they stand at the table's left side, facing it, outside the robot's reach
    assert second.origin_world[1] > _cell().table.center[1] + _cell().table.size[1] / 2
    assert np.linalg.norm(second.origin_world[:2]) > 0.85
    people.notify_block_placed("D", 2.0)
    people.notify_block_placed("B", 2.0)
    for t in np.arange(0.0, 12.0, 1 / FPS):
        f = people.frame_at(float(t))
        assert f is not None and f.body_ids == (OPERATOR_ID, SECOND_OPERATOR_ID)
    fetches = {i: [a.station for a in op.actions if a.kind == "fetch"] for i, op in people.operators.items()}
    assert fetches == {OPERATOR_ID: ["B"], SECOND_OPERATOR_ID: ["D"]}
    d = np.asarray(_cell().drop_stations[3].xyz)
    reach = next(a for a in second.actions if a.kind == "fetch")
    assert np.linalg.norm(np.asarray(reach.target_world)[:2] - d[:2]) < 1e-6
    # the right side fetches A; an explicit list wins
    right = Scenario.model_validate({"second_operator": {"side": "right"}})
    assert _people(right).station_owner["A"] == SECOND_OPERATOR_ID
    listed = Scenario.model_validate({"second_operator": {"stations": ["C", "D"]}})
    assert [k for k, v in _people(listed).station_owner.items() if v == SECOND_OPERATOR_ID] == ["C", "D"]
    with pytest.raises(ScenarioError, match="not drop stations"):
        _people(Scenario.model_validate({"second_operator": {"stations": ["Z"]}}))


def test_the_same_seeds_give_the_same_people() -> None:
    both = Scenario.model_validate(
        {"passers_by": {"count": 2, "enter_from": ["left", "right"]}, "second_operator": {}}
    )
    a, b = _people(both), _people(both)
    ts = np.arange(0.0, 60.0, 0.25)
    for t in ts:
        fa, fb = a.frame_at(float(t)), b.frame_at(float(t))
        assert fa is not None and fb is not None
        assert fa.body_ids == fb.body_ids and np.array_equal(fa.joints, fb.joints)
    # the bodies come from the participant's seed, the passes from the trial's
    c = _people(both, seed=6)
    assert c.walkers[2].params == a.walkers[2].params and c.walkers[3].params == a.walkers[3].params
    assert c.operators[SECOND_OPERATOR_ID].params == a.operators[SECOND_OPERATOR_ID].params
    closest = [[p.t_closest for p in x.walkers[2].passes_until(100.0)] for x in (a, c)]
    assert closest[0] != closest[1]
    d = _people(both, participant_seed=4)
    assert d.walkers[2].params != a.walkers[2].params
    assert a.walkers[2].params != a.walkers[3].params  # two distinct walkers
    assert a.operators[OPERATOR_ID].params == OperatorParams.draw(3)  # the operator is the one of the seed


def test_the_tracker_keeps_every_body_and_its_id_and_tracks_the_operator_as_alone() -> None:
    people = _people("scenario_passer_by.toml")
    model = TrackerModel(latency_s=0.06, noise_m=0.01, drop_p=0.0, burst_p=0.0)
    tracked = TrackedSource(people, model, seed=9)
    alone = TrackedSource(people.operators[OPERATOR_ID], model, seed=9)
    volume = CellVolume.from_workcell(_cell())
    walker_seen = 0
    for t in np.arange(0.1, 60.0, 1 / FPS):
        f, g = tracked.frame_at(float(t)), alone.frame_at(float(t))
        assert f is not None and g is not None and f.t == g.t
        assert f.body_ids == people.body_ids_at(f.t)
        assert np.array_equal(f.body(0).joints, g.joints)  # the operator's noise is as it was alone
        assert np.all(volume.contains(f.joints))  # the frame checks never lose a frame for a walker
        if f.bodies == 2:
            walker_seen += 1
            err = f.body(1).joints - people.walkers[FIRST_WALKER_ID].pose_at(f.t)
            assert 0.0 < np.abs(err).max() < 0.06
            assert not np.allclose(err, f.body(0).joints - g.joints)  # noise of its own
    assert walker_seen > 30


def test_the_oracle_forecasts_every_body_with_its_id() -> None:
    people = _people("scenario_passer_by.toml")
    walker = people.walkers[FIRST_WALKER_ID]
    t = walker.passes_until(60.0)[0].t_closest
    t = round(t * FPS) / FPS
    frame = people.frame_at(t)
    assert frame is not None and frame.body_ids == (OPERATOR_ID, FIRST_WALKER_ID)
    fc = PeopleOracle(people, horizon=30).update(frame)
    assert fc.body_ids == frame.body_ids and fc.joints.shape == (31, 2 * NUM_JOINTS, 3)
    assert np.array_equal(fc.joints[0], frame.joints)
    for k in (1, 15, 30):
        assert np.allclose(fc.joints[k, NUM_JOINTS:], walker.walking_pose(frame.t + k / FPS))
        operator = people.operators[OPERATOR_ID].pose_at(frame.t + k / FPS)
        assert np.allclose(fc.joints[k, :NUM_JOINTS], operator)
