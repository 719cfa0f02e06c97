"""``hrc hmp eval`` on simulated operators: a held-out source with the same report as the clips."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from app.cli import app as cli_app


def test_eval_on_simulated_operators_has_the_clips_report_shape() -> None:
    r = CliRunner().invoke(
        cli_app, ["hmp", "eval", "--sim-operators", "2", "--sim-seed", "3", "--sim-duration", "3", "--json"]
    )
    assert r.exit_code == 0, r.output
    report = json.loads(r.output)
    assert "seeds 3..4, 3 s each" in report["clips"] and "tuning" not in report["clips"]
    assert report["windows"] == 2 * (90 - 40 + 1)
    assert set(report["mpjpe_mm"]) == {"graphmixer", "constant_velocity", "zero_velocity"}
    forecast = report["forecast"]
    assert set(forecast["mpjpe_mm"]) == set(forecast["coverage"]) == set(report["mpjpe_mm"]["graphmixer"])
    assert forecast["coverage_target"] == 0.95 and forecast["forecasts"] == report["windows"]
    assert all(0.0 <= c <= 1.0 for c in forecast["coverage"].values())
    assert forecast["margin_prior"].startswith("hmp_graphmixer.quantiles.json")
    # per clip, against the better baseline over the same forecasts
    assert [c["clip"] for c in forecast["per_clip"]] == ["sim/sim_operator_3", "sim/sim_operator_4"]
    assert sum(c["forecasts"] for c in forecast["per_clip"]) == forecast["forecasts"]
    worst = forecast["worst_clip"]
    ratio = max(r for c in forecast["per_clip"] for r in c["ratio"].values())
    assert worst["ratio"] == ratio and worst["best_baseline"] in ("constant_velocity", "zero_velocity")
    clip = next(c for c in forecast["per_clip"] if c["clip"] == worst["clip"])
    assert clip["ratio"][str(worst["horizon_ms"])] == ratio
    assert worst["coverage"] == clip["coverage"][str(worst["horizon_ms"])]


def test_eval_says_when_the_seeds_are_tuning_seeds() -> None:
    r = CliRunner().invoke(
        cli_app,
        ["hmp", "eval", "--sim-operators", "1", "--sim-seed", "1000", "--sim-duration", "2", "--json"],
    )
    assert r.exit_code == 0, r.output
    assert "tuning seeds 1000-1999: not a held-out evaluation" in json.loads(r.output)["clips"]
