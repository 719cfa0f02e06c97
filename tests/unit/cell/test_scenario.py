"""Scenario files load, and a file that cannot be used is refused with a message that says why."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from app.cell.scenario import Scenario, ScenarioError, load_scenario
from app.config import Settings

EXAMPLES = Path(__file__).resolve().parents[3] / "examples"


def test_the_shipped_examples_load() -> None:
    walk = load_scenario(EXAMPLES / "scenario_passer_by.toml")
    assert walk.name == "scenario_passer_by" and walk.second_operator is None
    assert walk.passers_by is not None
    assert walk.passers_by.count == 1 and walk.passers_by.interval_s == [20.0, 40.0]
    assert walk.passers_by.clearance_m[1] <= 0.5 and walk.passers_by.reach_m == 0.85
    second = load_scenario(EXAMPLES / "scenario_second_operator.toml")
    assert second.passers_by is None and second.second_operator is not None
    assert second.second_operator.side == "left"


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "scenario.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("[passers_by\ncount = 1", "not valid TOML"),
        ("[passers_by]\ncout = 2\n", "passers_by.cout"),
        ("[passers_by]\ninterval_s = [40.0, 20.0]\n", "interval_s = [40.0, 20.0]"),
        ("[passers_by]\nspeed_mps = [1.0, 9.0]\n", "passers_by.speed_mps"),
        ("[passers_by]\nenter_from = ['roof']\n", "passers_by.enter_from"),
        ("[second_operator]\nside = 'up'\n", "second_operator.side"),
        ("name = 'nobody'\n", "[passers_by] and/or [second_operator]"),
        ("[crowd]\ncount = 3\n", "crowd"),
    ],
)
def test_a_bad_file_is_refused_with_the_reason(tmp_path: Path, text: str, needle: str) -> None:
    p = _write(tmp_path, text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(p)
    assert str(p) in str(err.value) and needle in str(err.value)


def test_a_missing_file_is_an_error_never_the_default(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match="cannot read the scenario file"):
        load_scenario(tmp_path / "nope.toml")
    with pytest.raises(ValidationError, match=r"scenario file .* does not exist"):
        Settings(scenario=tmp_path / "nope.toml")


def test_the_setting_defaults_to_no_scenario_and_takes_a_file(tmp_path: Path) -> None:
    assert Settings().scenario is None
    p = _write(tmp_path, "[second_operator]\n")
    assert Settings(scenario=p).scenario == p.resolve()
    assert Scenario.model_validate({"second_operator": {}}).second_operator is not None


def test_simulate_and_study_take_a_scenario_file_and_refuse_a_wrong_one(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import app
    from app.study.repository import open_repository

    runner = CliRunner()
    missing = runner.invoke(app, ["simulate", "--duration", "1", "--scenario", str(tmp_path / "no.toml")])
    assert missing.exit_code != 0 and "no.toml" in missing.output
    bad = _write(tmp_path, "[passers_by]\ninterval_s = [30.0, 10.0]\n")
    refused = runner.invoke(
        app, ["simulate", "--duration", "1", "--method", "reactive", "--scenario", str(bad)]
    )
    assert refused.exit_code == 2 and str(bad) in refused.output and "interval_s" in refused.output
    url = f"sqlite:///{tmp_path / 'study.db'}"
    base = ["study", "--participants", "1", "--duration", "0.5", "--workers", "0", "--engine", "inline"]
    missing = runner.invoke(
        app, [*base, "--no-progress", "--url", url, "--scenario", str(tmp_path / "no.toml")]
    )
    assert missing.exit_code != 0 and "no.toml" in missing.output
    scenario = EXAMPLES / "scenario_second_operator.toml"
    ran = runner.invoke(app, [*base, "--no-progress", "--url", url, "--scenario", str(scenario)])
    assert ran.exit_code == 0, ran.output
    repo = open_repository(url)
    try:  # the trials record the scenario they ran in (whatever the decision layer made of it)
        trials = repo.list_trials()
        assert len(trials) == 2 and all(t.settings["scenario"] == str(scenario.resolve()) for t in trials)
    finally:
        repo.close()
