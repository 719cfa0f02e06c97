"""The layout check (``hrc cell check``): where the speed governor lets the robot work beside the person.

The governor's speed for a part at rest (:meth:`GovernorModel.max_speed`) is checked against the scale it
gives a moving part (:meth:`GovernorModel.scale`); the check of the task poses on the shipped cell against
a person standing far away, on a drop station, and the simulated participants at work; the suggestion of
where to move a drop station that the person's work blocks.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from app.cli import app as cli_app
from app.config import Settings, load_workcell
from app.control.engine import EngineOptions, governor_model, supervisor_config
from app.control.layout import check_layout, suggest_stations
from app.control.stack import PlanningStack
from app.planning.collision import HUMAN_CAPSULES
from app.prediction.skeleton import JOINT_INDEX, JOINTS
from tests.unit.planning.test_collision import _standing_person
from tests.unit.planning.test_ssm_timing import governor


@pytest.fixture(scope="module")
def model(stack: PlanningStack):
    settings, options = Settings(), EngineOptions()
    return governor_model(settings, stack.ssm, supervisor_config(settings, "proactive", options), options)


def _still(joints: np.ndarray, frames: int = 30) -> np.ndarray:
    """``joints`` (J, 3) held for ``frames`` frames."""
    return np.repeat(joints[None], frames, axis=0)


def test_the_speed_for_a_part_is_the_one_the_governor_scales_a_moving_part_to() -> None:
    g = governor()
    sep = np.array([0.2, 0.35, 0.5, 0.8, 1.2])
    for v_h in (0.0, 0.3, 1.0):
        v = g.max_speed(sep, v_h)
        assert np.all(np.diff(v) >= 0)  # farther: faster
        assert np.all(g.max_speed(sep, v_h + 0.5) <= v + 1e-12)  # a faster person: slower
        for d, v_d in zip(sep, v, strict=True):
            # a part moving at 1 m/s at scale 1 is scaled to the speed the governor allows it (within its
            # grids: 3 m/s over 96 speeds, 40 scales)
            s = g.scale(np.array([d]), np.array([v_h]), np.array([1.0]), 0.0)
            assert s == pytest.approx(min(v_d, 1.0), abs=0.04)
    assert g.max_speed(0.11, 0.0) == 0.0  # within S_p(0) of a still person: no speed at all


def test_a_person_far_away_leaves_every_task_pose_free(stack: PlanningStack, model) -> None:
    far = _still(_standing_person(3.5, 0.0))
    report = check_layout(stack, model, [far], fps=30.0)
    assert {p.name for p in report.poses} == set(stack.roadmap.station_nodes)
    assert report.frames == 27  # each first speed window (3 frames at 30 Hz) measures no speed
    for p in report.poses:
        assert p.free == 1.0 and p.allowed_speed_mps[0] >= 0.1 and p.separation_m[0] > 2.0, p


def test_a_person_reaching_into_a_drop_station_blocks_it(stack: PlanningStack, model) -> None:
    cell = stack.cell
    b = np.asarray(next(s.xyz for s in cell.drop_stations if s.name == "B"))
    person = _standing_person(1.3, 0.0)
    person = person + (b - person[JOINT_INDEX["r_hand"]])  # the right hand on station B
    checked = check_layout(stack, model, [_still(person)], fps=30.0)
    report = {p.name: p for p in checked.poses}
    assert report["B"].free == 0.0 and report["B"].separation_m[1] < 0.1
    assert report["B"].allowed_speed_mps == (0.0, 0.0)
    # the zone: no speed asked of a pose closer than it to a still person is allowed
    assert all(p.free == 0.0 for p in report.values() if p.separation_m[1] < checked.zone_m - 0.02)


def test_a_hand_at_a_station_leaves_the_robot_its_permissible_speed_and_a_head_does_not(
    stack: PlanningStack, model
) -> None:
    """Power and force limiting in the check, as in the governor: a hand reaching to a station far from
    the rest of the body lets the robot move there at the slowest permissible speed of the limb's regions;
    the same reach with SSM alone, or a head there, allows nothing."""
    import dataclasses

    b = np.asarray(next(s.xyz for s in stack.cell.drop_stations if s.name == "B"))
    person = _standing_person(2.6, 0.0)  # far across the table ...
    for name in ("r_elbow", "r_wrist", "r_hand"):  # ... but for a forearm and hand laid onto station B
        person[JOINT_INDEX[name]] = b + np.array({"r_elbow": [0.35, 0.0, 0.05]}.get(name, [0.0, 0.0, 0.0]))
    person[JOINT_INDEX["r_wrist"]] = b + np.array([0.06, 0.0, 0.02])
    arm = [HUMAN_CAPSULES.index(c) for c in ("r_shoulder-r_elbow", "r_elbow-r_wrist", "r_wrist-r_hand")]
    slowest_limb = float(model.caps_for(len(HUMAN_CAPSULES))[arm].min())
    assert slowest_limb > 1.0  # an upper arm, a forearm, a hand: about 1.1-1.4 m/s (app.safety.pfl)
    hand = {p.name: p for p in check_layout(stack, model, [_still(person)], fps=30.0).poses}["B"]
    assert hand.separation_m[1] < 0.1
    assert hand.allowed_speed_mps[1] >= 0.9 * slowest_limb and hand.free == 1.0
    ssm_alone = dataclasses.replace(model, pfl_caps_mps=())
    alone = {p.name: p for p in check_layout(stack, ssm_alone, [_still(person)], fps=30.0).poses}["B"]
    assert alone.allowed_speed_mps == (0.0, 0.0) and alone.free == 0.0
    head = _standing_person(2.6, 0.0)
    head = head + (b + np.array([0.0, 0.0, 0.45]) - head[JOINT_INDEX["head"]])  # a head above station B
    above = {p.name: p for p in check_layout(stack, model, [_still(head)], fps=30.0).poses}["B"]
    assert above.allowed_speed_mps == (0.0, 0.0) and above.free == 0.0


def test_a_station_free_where_it_is_stays_there(stack: PlanningStack, model) -> None:
    far = _still(_standing_person(3.5, 0.0))
    moves = suggest_stations(stack, model, [far], fps=30.0)
    assert [m.name for m in moves] == [s.name for s in stack.cell.drop_stations]
    for m in moves:
        assert m.free == 1.0 and m.shift_m == 0.0 and m.suggested_xyz == m.xyz and m.reach_change_m == 0.0


def test_a_blocked_station_is_moved_away_from_the_person_to_where_the_robot_may_work(
    stack: PlanningStack, model, tmp_path: Path
) -> None:
    cell = stack.cell
    b = np.asarray(next(s.xyz for s in cell.drop_stations if s.name == "B"))
    person = _standing_person(1.0, 0.0)  # at the table's edge, across from the robot
    moves = {m.name: m for m in suggest_stations(stack, model, [_still(person)], fps=30.0, target_free=1.0)}
    m = moves["B"]
    assert m.free == 0.0 and m.suggested_xyz is not None and m.shift_m is not None and m.shift_m > 0.0
    new = np.asarray(m.suggested_xyz)
    assert m.suggested_free == 1.0 and new[2] == pytest.approx(b[2])
    assert np.linalg.norm(new - b) == pytest.approx(m.shift_m)
    # away from the person (toward the robot), on the table, clear of the other stations
    assert new[0] < b[0] - 0.2
    tc, ts = np.asarray(cell.table.center), np.asarray(cell.table.size)
    assert np.all(np.abs(new[:2] - tc[:2]) <= ts[:2] / 2)
    others = [np.asarray(s.xyz) for s in cell.drop_stations if s.name != "B"]
    assert min(np.linalg.norm(new[:2] - o[:2]) for o in others) >= 0.09
    pickup = np.asarray(cell.conveyor.pickup.xyz)
    assert m.reach_change_m == pytest.approx(np.linalg.norm(new - pickup) - np.linalg.norm(b - pickup))
    # the layout check of the cell with B moved there agrees
    moved = cell.model_copy(
        update={
            "drop_stations": [
                s.model_copy(update={"xyz": list(new) if s.name == "B" else s.xyz})
                for s in cell.drop_stations
            ]
        }
    )
    from app.planning.roadmap import RoadmapConfig

    moved_stack = PlanningStack.build(
        moved,
        roadmap_config=RoadmapConfig(num_nodes=250),
        t_reaction_s=stack.ssm.t_reaction_s,
        cache_dir=tmp_path,
    )
    checked = {p.name: p for p in check_layout(moved_stack, model, [_still(person)], fps=30.0).poses}
    assert checked["B"].free == 1.0 and checked["B_approach"].free == 1.0
    # nothing within a short search
    short = suggest_stations(stack, model, [_still(person)], fps=30.0, target_free=1.0, max_shift_m=0.1)
    gone = {x.name: x for x in short}["B"]
    assert gone.suggested_xyz is None and gone.shift_m is None and gone.reach_change_m is None


def test_a_footprint_turns_with_its_box() -> None:
    import math

    from app.config import Box
    from app.control.layout import _within_footprint

    long_x = Box(center=[1.0, 0.0, 0.0], size=[1.0, 0.2, 0.1])
    long_y = Box(center=[1.0, 0.0, 0.0], size=[1.0, 0.2, 0.1], yaw=math.pi / 2)
    along_x, along_y = np.array([1.4, 0.0, 0.5]), np.array([1.0, 0.4, 0.5])  # the height does not count
    assert _within_footprint(along_x, long_x, 0.0) and not _within_footprint(along_y, long_x, 0.0)
    assert _within_footprint(along_y, long_y, 0.0) and not _within_footprint(along_x, long_y, 0.0)
    # grown by 5 cm it reaches a point 4 cm past its side; shrunk by 5 cm, a point 4 cm inside is out
    assert _within_footprint(np.array([1.0, 0.14, 0.0]), long_x, 0.05)
    assert not _within_footprint(np.array([1.0, 0.06, 0.0]), long_x, -0.05)


def test_suggest_refuses_impossible_targets(stack: PlanningStack, model) -> None:
    far = [_still(_standing_person(3.5, 0.0))]
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="target_free must be in"):
            suggest_stations(stack, model, far, fps=30.0, target_free=bad)
    with pytest.raises(ValueError, match="step_m and max_shift_m must be > 0"):
        suggest_stations(stack, model, far, fps=30.0, step_m=0.0)


def test_check_refuses_recordings_it_cannot_measure(stack: PlanningStack, model) -> None:
    with pytest.raises(ValueError, match="no recording has more than 3 frames"):
        check_layout(stack, model, [_still(_standing_person(3.5), frames=3)], fps=30.0)
    with pytest.raises(ValueError, match=r"\(T, J, 3\), got \(30, 57\)"):
        check_layout(stack, model, [_still(_standing_person(3.5)).reshape(30, -1)], fps=30.0)
    lost = _still(_standing_person(3.5))
    lost[10] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        check_layout(stack, model, [lost], fps=30.0)


def test_cli_checks_the_shipped_cell(tmp_path: Path) -> None:
    res = CliRunner().invoke(
        cli_app, ["cell", "check", "--participants", "1", "--duration", "8", "--json"], catch_exceptions=False
    )
    assert res.exit_code == 0, res.output
    out = json.loads(res.output.strip().splitlines()[-1])
    poses = out["poses"]
    assert {"pickup", "A", "B", "C", "D", "home"} <= set(poses)
    assert 0.3 < out["zone_m"] < 1.5 and out["frames"] > 200
    # the pickup is farther from the person at work than the drop stations they fetch from
    stations = [poses[s]["separation_m"]["p50"] for s in "ABCD"]
    assert poses["pickup"]["separation_m"]["p50"] > max(stations)
    assert poses["pickup"]["free"] >= max(poses[s]["free"] for s in "ABCD")
    assert "suggestions" not in out
    # --suggest: where each drop station could go (the simulated participant blocks them all)
    sug = CliRunner().invoke(
        cli_app,
        ["cell", "check", "--participants", "1", "--duration", "8", "--suggest", "--json"],
        catch_exceptions=False,
    )
    assert sug.exit_code == 0, sug.output
    got_sug = json.loads(sug.output.strip().splitlines()[-1])
    assert got_sug["target_free"] == 0.75 and set(got_sug["suggestions"]) == set("ABCD")
    shipped = {s.name: [round(v, 3) for v in s.xyz] for s in load_workcell().drop_stations}
    for name, m in got_sug["suggestions"].items():
        assert m["xyz"] == shipped[name]
        assert m["suggested_xyz"] is None or m["suggested_free"] >= 0.75
    text = CliRunner().invoke(
        cli_app, ["cell", "check", "--participants", "1", "--duration", "8", "--suggest"]
    )
    assert text.exit_code == 0 and "B: " in text.output
    # a recording in the format of `hrc export --clips`: a person far away leaves every pose free
    np.savez_compressed(
        tmp_path / "far.npz",
        positions=_still(_standing_person(3.5, 0.0), frames=60).astype(np.float32),
        fps=np.float64(30.0),
        joint_names=np.array(JOINTS),
    )
    far = CliRunner().invoke(cli_app, ["cell", "check", "--clip", str(tmp_path / "far.npz"), "--json"])
    assert far.exit_code == 0, far.output
    got = json.loads(far.output.strip().splitlines()[-1])
    assert got["frames"] == 57 and all(p["free"] == 1.0 for p in got["poses"].values())
    # a clip recorded elsewhere (10 m away) is placed in the operator's area with --place
    np.savez_compressed(
        tmp_path / "elsewhere.npz",
        positions=_still(_standing_person(10.0, 4.0), frames=60).astype(np.float32),
        fps=np.float64(30.0),
        joint_names=np.array(JOINTS),
    )
    args = ["cell", "check", "--clip", str(tmp_path / "elsewhere.npz"), "--json"]
    away = json.loads(CliRunner().invoke(cli_app, args).output.strip().splitlines()[-1])
    placed = json.loads(CliRunner().invoke(cli_app, [*args, "--place"]).output.strip().splitlines()[-1])
    assert away["poses"]["B"]["separation_m"]["p50"] > 8.0
    assert placed["poses"]["B"]["separation_m"]["p50"] < 1.0


def test_cli_names_a_missing_or_unreadable_clip_whatever_the_terminal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One plain error line with the whole path: a narrow terminal (COLUMNS=40) and a checkout 150
    characters deep neither cut nor fold it."""
    monkeypatch.setenv("COLUMNS", "40")
    deep = tmp_path / ("d" * max(150 - len(str(tmp_path)), 1))
    deep.mkdir()
    missing = deep / "nobody.npz"
    bad = CliRunner().invoke(cli_app, ["cell", "check", "--clip", str(missing)])
    assert bad.exit_code == 2, bad.output
    assert "nobody.npz" in bad.output and "does not exist" in bad.output and "--clip" in bad.output
    assert str(missing) in bad.output  # one plain line: the whole path, neither cut nor folded at 40 columns
    np.savez(deep / "wrong.npz", something=np.zeros(3))
    wrong = CliRunner().invoke(cli_app, ["cell", "check", "--clip", str(deep / "wrong.npz")])
    assert wrong.exit_code == 2 and "wrong.npz" in wrong.output and "Traceback" not in wrong.output
