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
    assert _shipped_with(tmp_path, shipped, "approach_height_m = 0.031").approach_height_m == pytest.approx(
        0.031
    )


def test_the_cell_sets_the_planners_joint_limits_within_the_arms(tmp_path: Path) -> None:
    from app.config import UR5E_Q_LIMIT
    from app.planning.kinematics import Q_MAX, Q_MIN, UR5e

    # the UR5e's: +-2 pi, the elbow +-pi (UR5e user manual, joint ranges); the kinematics take these
    assert np.allclose(UR5E_Q_LIMIT, [2 * np.pi] * 2 + [np.pi] + [2 * np.pi] * 3)
    assert np.array_equal(Q_MAX, UR5E_Q_LIMIT) and np.array_equal(Q_MIN, -Q_MAX)
    cell = load_workcell()
    lo, hi = cell.robot.joint_limits()
    assert hi[4] == 0.0 and lo[4] == pytest.approx(-np.pi, abs=1e-4)  # the shipped cell: wrist 2 in [-pi, 0]
    kin = UR5e.from_workcell(cell)
    q, valid = kin.ik_down(np.array([[0.6, 0.11, 0.15]]), yaw=0.0)
    assert valid.any() and np.all(q[valid][:, 4] <= 0.0)  # every usable branch keeps wrist 2 on its side
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
