from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from app.config import Settings, WorkCellError, load_workcell, rpy_to_matrix


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
