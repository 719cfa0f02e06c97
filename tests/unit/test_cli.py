"""Start-up errors a person can act on: one plain line naming the file and the field, no traceback, a
non-zero exit, whatever the terminal's width or the length of the path (a checkout 150 characters deep,
COLUMNS=40)."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from app.cli import app as cli_app

SHIPPED_CELL = Path(__file__).resolve().parents[2] / "app/assets/workcell.toml"


def deep_dir(tmp_path: Path, length: int = 150) -> Path:
    """A directory whose path is at least ``length`` characters long."""
    d = tmp_path / "deep"
    while len(str(d)) < length:
        d = d / ("x" * min(40, length - len(str(d))))
    d.mkdir(parents=True)
    return d


def _errors(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("error:")]


@pytest.mark.parametrize("case", ["missing", "invalid", "not_toml"])
def test_serve_with_a_bad_work_cell_says_which_file_and_field_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: str
) -> None:
    monkeypatch.setenv("COLUMNS", "40")
    d = deep_dir(tmp_path)
    cell = d / "my-cell.toml"
    if case == "invalid":
        cell.write_text(
            SHIPPED_CELL.read_text().replace("size = [1.5, 1.6, 0.05]", "size = [1.5, -1.6, 0.05]")
        )
    elif case == "not_toml":
        cell.write_text("name = 'x'\n[table\n")
    env = {"HRC_WORKCELL": str(cell), "HRC_DATA_DIR": str(tmp_path / "var")}
    res = CliRunner().invoke(cli_app, ["serve"], env=env)
    assert res.exit_code == 2, res.output
    (line,) = _errors(res.output)
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert str(cell) in line  # the whole path, never cut
    token = {"missing": "cannot read", "invalid": "table.size.1", "not_toml": "not valid TOML"}[case]
    assert token in line and "HRC_WORKCELL" in line


def test_serve_with_an_invalid_setting_names_it_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "40")
    missing = deep_dir(tmp_path) / "weights.pt"
    res = CliRunner().invoke(cli_app, ["serve"], env={"HRC_HMP_WEIGHTS": str(missing), "HRC_PORT": "8000"})
    assert res.exit_code == 2 and "Traceback" not in res.output
    (line,) = _errors(res.output)
    assert "hmp_weights" in line and "weights.pt" in line and str(missing) in line


def test_serve_with_a_taken_viewer_port_names_the_port_and_the_setting_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another program holds HRC_VISER_PORT: hrc serve stops before it starts anything (viser used to move
    to the next port with only an INFO line)."""
    import socket

    from app.api import server as server_mod

    monkeypatch.setenv("COLUMNS", "40")
    started: list[object] = []
    monkeypatch.setattr(server_mod, "run_server", lambda *a, **k: started.append(a))
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        env = {"HRC_VISER_PORT": str(port), "HRC_DATA_DIR": str(tmp_path / "var"), "HRC_HOST": "127.0.0.1"}
        res = CliRunner().invoke(cli_app, ["serve"], env=env)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    (line,) = _errors(res.output)
    assert len(res.output.strip().splitlines()) == 1, res.output
    assert f"port {port} on 127.0.0.1 is in use" in line and "HRC_VISER_PORT" in line
    assert started == []


def test_serve_with_corrupt_predictor_weights_names_the_file_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Corrupt weights stop hrc serve (they used to start it on constant velocity with a warning), unless
    HRC_HMP_FALLBACK asks for the fallback."""
    from app.api import server as server_mod

    monkeypatch.setenv("COLUMNS", "40")
    started: list[object] = []
    monkeypatch.setattr(server_mod, "run_server", lambda *a, **k: started.append(a))
    weights = deep_dir(tmp_path) / "corrupt.pt"
    weights.write_bytes(b"not a checkpoint" * 64)
    import socket

    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        viser_port = free.getsockname()[1]
    env = {
        "HRC_HMP_WEIGHTS": str(weights),
        "HRC_DATA_DIR": str(tmp_path / "var"),
        "HRC_HOST": "127.0.0.1",
        "HRC_VISER_PORT": str(viser_port),
    }
    res = CliRunner().invoke(cli_app, ["serve"], env=env)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    (line,) = _errors(res.output)
    assert len(res.output.strip().splitlines()) == 1, res.output
    assert str(weights) in line and "HRC_HMP_WEIGHTS" in line and "HRC_HMP_FALLBACK" in line
    assert started == []
    res = CliRunner().invoke(cli_app, ["serve"], env={**env, "HRC_HMP_FALLBACK": "true"})
    assert res.exit_code == 0, res.output
    assert len(started) == 1


def test_cell_check_with_a_bad_work_cell_says_which_file_and_field(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("COLUMNS", "40")
    cell = deep_dir(tmp_path) / "cell.toml"
    cell.write_text(SHIPPED_CELL.read_text() + "\nbogus = 1\n")
    res = CliRunner().invoke(cli_app, ["cell", "check"], env={"HRC_WORKCELL": str(cell)})
    assert res.exit_code == 2 and "Traceback" not in res.output
    (line,) = _errors(res.output)
    assert "bogus" in line and "cell.toml" in line
