from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.config import Settings, WorkCell, WorkCellError, load_workcell, rpy_to_matrix


def test_default_workcell_loads() -> None:
    cell = load_workcell()
    assert len(cell.drop_stations) == 4
    assert cell.conveyor.pickup.name == "pickup"
    assert len(cell.static_boxes) == 3
    assert cell.fingerprint() == load_workcell().fingerprint()


def test_the_example_cell_with_the_stations_moved_differs_from_the_shipped_one_only_there() -> None:
    shipped = load_workcell()
    moved = load_workcell(Path(__file__).resolve().parents[2] / "examples/workcell_stations_moved.toml")
    assert [s.name for s in moved.drop_stations] == [s.name for s in shipped.drop_stations]
    for a, b in zip(moved.drop_stations, shipped.drop_stations, strict=True):
        assert a.xyz[2] == b.xyz[2] and a.xyz[0] < b.xyz[0] - 0.2  # toward the robot, at the same height
    same = {"drop_stations", "name"}
    assert moved.model_dump(exclude=same) == shipped.model_dump(exclude=same)


def test_malformed_workcell_names_field_and_reason(tmp_path: Path) -> None:
    text = (Path(__file__).resolve().parents[2] / "app/assets/workcell.toml").read_text()
    bad = text.replace("size = [1.5, 1.6, 0.05]", "size = [1.5, -1.6, 0.05]")
    p = tmp_path / "cell.toml"
    p.write_text(bad)
    with pytest.raises(WorkCellError) as err:
        load_workcell(p)
    assert "table.size.1" in str(err.value)
    assert "greater than 0" in str(err.value)


def test_unknown_field_and_bad_toml_rejected(tmp_path: Path) -> None:
    p = tmp_path / "cell.toml"
    p.write_text("name = 'x'\n[table\n")
    with pytest.raises(WorkCellError, match="not valid TOML"):
        load_workcell(p)
    text = (Path(__file__).resolve().parents[2] / "app/assets/workcell.toml").read_text()
    p.write_text(text + "\nbogus = 1\n")
    with pytest.raises(WorkCellError, match="bogus"):
        load_workcell(p)
    with pytest.raises(WorkCellError, match="cannot read"):
        load_workcell(tmp_path / "missing.toml")


def _shipped_with(tmp_path: Path, old: str, new: str) -> WorkCell:
    """The shipped cell's file with ``old`` replaced by ``new``, loaded."""
    text = (Path(__file__).resolve().parents[2] / "app/assets/workcell.toml").read_text()
    assert old in text
    p = tmp_path / "cell.toml"
    p.write_text(text.replace(old, new))
    return load_workcell(p)


def test_the_approach_must_lift_the_open_fingertips_over_the_part(tmp_path: Path) -> None:
    cell = load_workcell()
    # the shipped gripper: fingertips 161 mm from the flange, the TCP at 150 mm, a 40 mm block centred on it
    assert cell.tool.fingertip_depth_m == pytest.approx(0.011)
    assert cell.approach_height_m >= 0.011 + 0.02
    shipped = "approach_height_m = 0.06"
    with pytest.raises(WorkCellError, match=r"approach_height_m.*must be >= 0\.031 m"):
        _shipped_with(tmp_path, shipped, "approach_height_m = 0.03")
    lowest = _shipped_with(tmp_path, "approach_retreat_m = 0.04", "approach_retreat_m = 0.0")
    assert lowest.approach_retreat_m == 0.0
    text = (tmp_path / "cell.toml").read_text().replace(shipped, "approach_height_m = 0.031")
    (tmp_path / "cell.toml").write_text(text)
    assert load_workcell(tmp_path / "cell.toml").approach_height_m == pytest.approx(0.031)


def test_the_retreat_from_a_station_keeps_the_open_fingers_off_the_released_part(tmp_path: Path) -> None:
    cell = load_workcell()
    # the shipped gripper opens its pads 85 mm apart (the 2F-85's stroke) around a 40 mm block: 22.5 mm of
    # room on either side. Its fingertips must rise 31 mm to clear the block; on a slope of retreat / height
    # they move 31 mm * slope toward it meanwhile, so at 0.06 m of height the retreat may be 0.0435 m at most
    assert cell.tool.finger_gap_m == pytest.approx(0.0225)
    assert cell.approach_retreat_m == pytest.approx(0.04)
    shipped = "approach_retreat_m = 0.04"
    ok = _shipped_with(tmp_path, shipped, "approach_retreat_m = 0.0435")
    with pytest.raises(WorkCellError, match=r"approach_retreat_m = 0.045 m.*must be <= 0\.0435 m"):
        _shipped_with(tmp_path, shipped, "approach_retreat_m = 0.045")
    # higher, the same retreat is a gentler slope
    higher = (
        (tmp_path / "cell.toml").read_text().replace("approach_height_m = 0.06", "approach_height_m = 0.07")
    )
    (tmp_path / "cell.toml").write_text(higher)
    assert load_workcell(tmp_path / "cell.toml").approach_retreat_m == pytest.approx(0.045)
    # the approach pose lies back from the station, away from the work spot in the table's plane, and as high
    spot = np.asarray(ok.operator.work_spot[:2])
    for st in ok.drop_stations:
        off = ok.approach_offset(st.name)
        assert off[2] == pytest.approx(0.06)
        assert np.linalg.norm(off[:2]) == pytest.approx(0.0435)
        away = np.asarray(st.xyz[:2]) - spot
        assert np.dot(off[:2], away) == pytest.approx(0.0435 * np.linalg.norm(away))
    # the pickup's approach stays straight up; an unknown station is refused, never given a default
    assert np.allclose(ok.approach_offset(ok.conveyor.pickup.name), [0.0, 0.0, 0.06])
    with pytest.raises(KeyError, match="no station 'Z'"):
        ok.approach_offset("Z")
    # a part wider than the stroke does not fit the gripper
    with pytest.raises(WorkCellError, match="does not fit between the open fingers"):
        _shipped_with(tmp_path, "part_size_m = [0.04, 0.04, 0.04]", "part_size_m = [0.09, 0.09, 0.04]")


def test_the_cell_sets_the_planners_joint_limits_within_the_arms(tmp_path: Path) -> None:
    from app.config import UR5E_Q_LIMIT
    from app.planning.kinematics import Q_MAX, Q_MIN, UR5e

    # the UR5e's: +-2 pi, the elbow +-pi (UR5e user manual, joint ranges); the kinematics take these
    assert np.allclose(UR5E_Q_LIMIT, [2 * np.pi] * 2 + [np.pi] + [2 * np.pi] * 3)
    assert np.array_equal(Q_MAX, UR5E_Q_LIMIT) and np.array_equal(Q_MIN, -Q_MAX)
    cell = load_workcell()
    lo, hi = cell.robot.joint_limits()
    assert hi[4] == 0.0 and lo[4] == pytest.approx(-np.pi, abs=1e-4)  # the shipped cell: wrist 2 in [-pi, 0]
    assert lo[2] == 0.0 and hi[2] == pytest.approx(np.pi, abs=1e-4)  # ... and the elbow in [0, pi]
    kin = UR5e.from_workcell(cell)
    q, valid = kin.ik_down(np.array([[0.6, 0.11, 0.15]]), yaw=0.0)
    assert valid.any() and np.all(q[valid][:, 4] <= 0.0)  # every usable branch keeps wrist 2 on its side
    assert np.all(q[valid][:, 2] >= 0.0)  # and the elbow on home_q's
    with pytest.raises(WorkCellError, match=r"home_q\[4\] = -1.5708 lies outside"):
        _shipped_with(tmp_path, "6.2832, 0.0, 6.2832]", "6.2832, -2.0, 6.2832]")
    with pytest.raises(WorkCellError, match="robot joint 1: limits"):
        _shipped_with(tmp_path, "q_max = [6.2832,", "q_max = [7.0,")


def test_rpy_matrix_is_rotation() -> None:
    R = rpy_to_matrix([0.3, -0.2, 1.1])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HRC_PORT", "9001")
    monkeypatch.setenv("HRC_ROBOT", "rtde")
    s = Settings(_env_file=None)
    assert s.port == 9001 and s.robot == "rtde"
    monkeypatch.setenv("HRC_ROBOT", "kuka")
    with pytest.raises(ValueError, match="robot"):
        Settings(_env_file=None)


def test_unknown_hrc_variables_name_the_nearest_setting() -> None:
    from app.config import unknown_environment_settings

    env = {
        "HRC_API_TOKN": "x",
        "HRC_PORT": "8001",
        "HRC_QWERTY": "1",
        "PATH": "/bin",
        "hrc_deadline_s": "0.1",
    }
    assert unknown_environment_settings(env) == [
        "HRC_API_TOKN is not a setting; did you mean HRC_API_TOKEN?",
        "HRC_QWERTY is not a setting; the settings are listed in the README (Settings)",
    ]
    assert unknown_environment_settings({"HRC_STRICT_SETTINGS": "true"}) == []


def test_the_cli_warns_about_a_misspelt_variable_or_stops_when_strict() -> None:
    from typer.testing import CliRunner

    from app.cli import app as cli_app

    warned = CliRunner().invoke(cli_app, ["bench", "--list"], env={"HRC_API_TOKN": "secret"})
    assert warned.exit_code == 0, warned.output
    assert "warning: HRC_API_TOKN is not a setting; did you mean HRC_API_TOKEN?" in warned.output
    assert "kinematics" in warned.output  # the command ran
    strict = {"HRC_API_TOKN": "secret", "HRC_STRICT_SETTINGS": "true"}
    stopped = CliRunner().invoke(cli_app, ["bench", "--list"], env=strict)
    assert stopped.exit_code == 2 and "error: HRC_API_TOKN" in stopped.output
    assert "kinematics" not in stopped.output
    bad = CliRunner().invoke(cli_app, ["bench", "--list"], env={"HRC_STRICT_SETTINGS": "maybe"})
    assert bad.exit_code == 2 and "HRC_STRICT_SETTINGS must be true or false" in bad.output
