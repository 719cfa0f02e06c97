"""The simulated population is read from a TOML file; bad files are explained, not replaced."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from app.cell.operator_sim import OperatorParams
from app.cell.population import DEFAULT_POPULATION_PATH, PopulationError


def test_the_shipped_population_draws_reproducible_valid_participants() -> None:
    pop = OperatorParams.population()
    assert OperatorParams.draw(11) == OperatorParams.draw(11, pop)
    drawn = [OperatorParams.draw(s) for s in range(200)]
    heights = [p.height_m for p in drawn]
    assert min(heights) >= 1.52 and max(heights) <= 1.95
    assert 0.7 < sum(p.handedness == "right" for p in drawn) / len(drawn) < 0.97
    assert all(0.3 <= p.reaction_s <= 1.2 for p in drawn)


def test_a_population_file_changes_the_participants(tmp_path: Path) -> None:
    text = DEFAULT_POPULATION_PATH.read_text().replace(
        "[reaction_s]\nuniform = { lo = 0.3, hi = 1.2 }", "[reaction_s]\nuniform = { lo = 2.0, hi = 2.5 }"
    )
    path = tmp_path / "slow.toml"
    path.write_text(text)
    slow = OperatorParams.population(path)
    assert all(2.0 <= OperatorParams.draw(s, slow).reaction_s <= 2.5 for s in range(50))
    assert OperatorParams.draw(3, slow).height_m == OperatorParams.draw(3).height_m  # same draw order


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t + "\n[wings]\nuniform = { lo = 0, hi = 1 }\n", "unknown parameter"),
        (lambda t: t.replace("[sway_m]\nuniform = { lo = 0.005, hi = 0.015 }", ""), "missing \\['sway_m'\\]"),
        (lambda t: t.replace("beta = { a = 2.0, b = 2.0 }", "gamma = { k = 2.0 }"), "is not one of"),
        (lambda t: t.replace("beta = { a = 2.0, b = 2.0 }", "beta = { a = 2.0 }"), "missing \\['b'\\]"),
        (lambda t: t.replace("lo = 0.3, hi = 1.2", "lo = 30.0, hi = 31.0"), "invalid participant"),
        (lambda t: t + "\n[[broken", "not valid TOML"),
    ],
)
def test_bad_population_files_are_explained(tmp_path: Path, edit, message: str) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "bad.toml"
    path.write_text(edit(DEFAULT_POPULATION_PATH.read_text()))
    with pytest.raises(PopulationError, match=message) as info:
        OperatorParams.population(path)
    assert str(path) in str(info.value)


def test_a_missing_population_file_is_an_error_not_the_default(tmp_path: Path) -> None:
    with pytest.raises(PopulationError, match="does not exist"):
        OperatorParams.population(tmp_path / "nope.toml")


def test_simulate_takes_a_population_file_and_refuses_a_wrong_path(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from app.cli import app

    runner = CliRunner()
    missing = runner.invoke(app, ["simulate", "--duration", "1", "--population", str(tmp_path / "no.toml")])
    assert missing.exit_code != 0 and "no.toml" in missing.output
    bad = tmp_path / "bad.toml"
    bad.write_text("[height_m]\nuniform = { lo = 1.6, hi = 1.7 }\n")
    refused = runner.invoke(
        app, ["simulate", "--duration", "1", "--method", "reactive", "--population", str(bad)]
    )
    assert refused.exit_code == 2 and "missing" in refused.output and str(bad) in refused.output
    ok = runner.invoke(
        app,
        [
            "simulate",
            "--duration",
            "2",
            "--method",
            "reactive",
            "--json",
            "--population",
            str(DEFAULT_POPULATION_PATH),
        ],
    )
    assert ok.exit_code == 0, ok.output


def test_study_takes_a_population_file_and_refuses_a_wrong_path(tmp_path: Path) -> None:
    import json

    from typer.testing import CliRunner

    from app.cli import app
    from app.study.repository import open_repository

    url = f"sqlite:///{tmp_path / 'study.db'}"
    runner = CliRunner()
    base = ["study", "--participants", "1", "--duration", "1", "--workers", "0", "--engine", "inline"]
    missing = runner.invoke(
        app, [*base, "--no-progress", "--url", url, "--population", str(tmp_path / "no.toml")]
    )
    assert missing.exit_code != 0 and "no.toml" in missing.output
    ok = runner.invoke(
        app, [*base, "--no-progress", "--url", url, "--population", str(DEFAULT_POPULATION_PATH)]
    )
    assert ok.exit_code == 0, ok.output
    assert json.loads(ok.output.strip().splitlines()[-1])["completed"] == 2
    repo = open_repository(url)
    try:
        trials = repo.list_trials()
        assert len(trials) == 2
        assert all(t.settings["population"] == str(DEFAULT_POPULATION_PATH) for t in trials)
    finally:
        repo.close()


def test_the_instructed_population_reaches_in_only_to_fetch() -> None:
    """``examples/population_instructed.toml``: the paper's participants, advised to minimise movements in
    front of the robot, make no spontaneous reaches across the table; everything else is drawn as in the
    shipped population, participant by participant."""
    from app.cell.operator_sim import SimulatedOperator
    from app.config import load_workcell

    path = Path(__file__).resolve().parents[3] / "examples/population_instructed.toml"
    instructed = OperatorParams.population(path)
    for seed in range(20):
        p, q = OperatorParams.draw(seed, instructed), OperatorParams.draw(seed)
        assert p.reach_rate_hz == 0.0 and q.reach_rate_hz > 0.0
        assert dataclasses.replace(p, reach_rate_hz=q.reach_rate_hz) == q
    cell = load_workcell()
    kinds = {}
    for params in (OperatorParams.draw(4, instructed), OperatorParams.draw(4)):
        op = SimulatedOperator(cell, params, seed=4)
        op.frame_at(120.0)
        kinds[params.reach_rate_hz == 0.0] = {a.kind for a in op.actions}
    assert "reach_across" not in kinds[True] and "reach_across" in kinds[False]
