"""Sweeps: spec validation, the plan and its keys, resumable runs, the unique key, the per-setting report.

The trials are fakes (deterministic metrics from the seeds) run inline; the real runtime and Ray run in
tests/integration/test_sweep_kill_resume.py.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import pytest
from typer.testing import CliRunner

from app.control.metrics import TrialEvent, TrialMetrics
from app.study.db import make_engine, upgrade_to_head
from app.study.repository import StudyRepository
from app.study.runner import TrialJob, TrialOutcome
from app.study.sweep import (
    SweepSpecError,
    parse_spec,
    plan_sweep,
    run_sweep,
    sweep_report,
    write_sweep_report,
)

SPEC = {"name": "d", "participants": 3, "duration_s": 5.0, "seed": 4, "grid": {"deadline_s": [0.1, 0.2]}}


def fake_trial(job: TrialJob) -> TrialOutcome:
    """Proactive completes 2 + (deadline in 10 ms) more tasks than reactive; p02 reactive fails."""
    if job.participant_code.endswith("p02") and job.method == "reactive" and job.settings.get("_fail"):
        return TrialOutcome(job.trial_id, None, error="RuntimeError: simulated crash")
    bonus = 2 + round(job.settings["deadline_s"] * 100) if job.method == "proactive" else 0
    metrics = TrialMetrics(
        method=job.method,  # type: ignore[arg-type]
        duration_s=5.0,
        completed_tasks=10 + job.participant_seed % 4 + bonus,
        stop_replans=1,
        online_replans=2,
        avg_planning_time_s=0.1,
        min_separation_m=0.4,
    )
    return TrialOutcome(
        job.trial_id,
        asdict(metrics),
        events=[TrialEvent(t=0.0, kind="trial_started", payload={"method": job.method})],
    )


_failing = {"n": 0}


def flaky_trial(job: TrialJob) -> TrialOutcome:
    """Fails p02's reactive trials on the first run only."""
    if job.participant_code.endswith("p02") and job.method == "reactive" and _failing["n"] == 0:
        return TrialOutcome(job.trial_id, None, error="RuntimeError: simulated crash")
    return fake_trial(job)


@pytest.fixture
def repo(tmp_path: Path) -> Iterator[StudyRepository]:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    upgrade_to_head(url)
    r = StudyRepository(make_engine(url))
    yield r
    r.close()


def test_the_plan_has_one_keyed_trial_per_setting_participant_and_method() -> None:
    spec = parse_spec(SPEC)
    plan = plan_sweep(spec)
    assert len(plan) == 2 * 3 * 2
    assert len({t.key for t in plan}) == len(plan)
    assert {t.label for t in plan} == {"deadline_s=0.1", "deadline_s=0.2"}
    assert all(t.job.settings["deadline_s"] in (0.1, 0.2) for t in plan)
    assert [t.key for t in plan] == [t.key for t in plan_sweep(parse_spec(SPEC))]  # deterministic
    # both methods of a participant share the seeds (paired)
    first = [t for t in plan if t.job.participant_code.endswith("p01") and t.label == "deadline_s=0.1"]
    assert {t.job.method for t in first} == {"proactive", "reactive"}
    assert len({(t.job.participant_seed, t.job.trial_seed) for t in first}) == 1


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"grid": {"deadlin_s": [0.1]}}, "deadlin_s is not a setting"),
        ({"grid": {"deadline_s": [5.0]}}, "setting 'deadline_s=5.0': deadline_s: Input should be less"),
        ({"grid": {"deadline_s": []}}, "must be a non-empty list"),
        ({"methods": ["magic"]}, "`methods` must be a non-empty subset"),
        ({"name": ""}, "non-empty `name`"),
        ({"settings": [{"deadline_s": 0.1}]}, "either as a \\[grid\\] table or as \\[\\[settings\\]\\]"),
        ({"participant": 3}, "unknown spec keys \\['participant'\\]"),
    ],
)
def test_an_invalid_spec_is_refused_with_what_was_wrong(change: dict, message: str) -> None:
    with pytest.raises(SweepSpecError, match=message):
        parse_spec({**SPEC, **change})


def test_a_list_of_settings_keeps_its_labels() -> None:
    spec = parse_spec(
        {
            "name": "l",
            "participants": 1,
            "settings": [{"label": "short", "deadline_s": 0.05}, {"anticipate_fetch": False}],
        }
    )
    assert [lab for lab, _ in spec.settings] == ["short", "anticipate_fetch=False"]


def test_a_sweep_run_again_runs_only_missing_or_failed_trials(repo: StudyRepository) -> None:
    spec = parse_spec(SPEC)
    _failing["n"] = 0
    first = run_sweep(spec, repo, engine="inline", workers=0, progress=False, trial_fn=flaky_trial)
    assert (first.planned, first.skipped, first.completed, first.failed) == (12, 0, 10, 2)
    _failing["n"] = 1
    second = run_sweep(spec, repo, engine="inline", workers=0, progress=False, trial_fn=flaky_trial)
    assert (second.skipped, second.completed, second.failed, second.duplicates) == (10, 2, 0, 0)
    third = run_sweep(spec, repo, engine="inline", workers=0, progress=False, trial_fn=flaky_trial)
    assert (third.skipped, third.completed) == (12, 0)
    assert repo.stored_trial_keys(prefix="d|") == {t.key for t in plan_sweep(spec)}
    rows = repo.metrics_rows(status="completed")
    assert len(rows) == 12


def test_a_key_is_stored_once_and_a_second_store_changes_nothing(repo: StudyRepository) -> None:
    spec = parse_spec({**SPEC, "participants": 1, "grid": {"deadline_s": [0.1]}})
    run_sweep(spec, repo, engine="inline", workers=0, progress=False, trial_fn=fake_trial)
    t = plan_sweep(spec)[0]
    trial = next(r for r in repo.metrics_rows(status="completed") if r["method"] == t.job.method)
    again = repo.store_keyed_trial(
        trial_key=t.key,
        setting_label=t.label,
        participant_id=trial["participant_id"],
        method=t.job.method,  # type: ignore[arg-type]
        session_id=None,
        order_index=0,
        seed=t.job.trial_seed,
        duration_s=5.0,
        settings={},
        metrics=fake_trial(t.job).metrics,  # type: ignore[arg-type]
        events=fake_trial(t.job).events,
    )
    assert again is None
    assert len(repo.metrics_rows(status="completed")) == 2


def test_the_per_setting_report_has_the_effect_per_setting(repo: StudyRepository, tmp_path: Path) -> None:
    spec = parse_spec(SPEC)
    run_sweep(spec, repo, engine="inline", workers=0, progress=False, trial_fn=fake_trial)
    rep = sweep_report(repo, "d")
    assert list(rep["settings"]) == ["deadline_s=0.1", "deadline_s=0.2"]
    for label, expected in (("deadline_s=0.1", 12.0), ("deadline_s=0.2", 22.0)):
        s = rep["settings"][label]
        eff = s["effects"]["completed_tasks"]
        assert eff["mean_difference"] == pytest.approx(expected)
        assert eff["n_pairs"] == 3 and eff["ci95"] == pytest.approx([expected, expected])
        assert s["values"] == {"deadline_s": float(label.split("=")[1])}
        assert s["n_participants"] == 3
    paths = write_sweep_report(rep, tmp_path / "rep")
    assert paths["effect_deadline_s"].stat().st_size > 0
    csv_lines = paths["csv"].read_text().splitlines()
    assert len(csv_lines) == 1 + 2 * len(rep["settings"]["deadline_s=0.1"]["metrics"]) * 2
    with pytest.raises(LookupError, match="no completed trial of the sweep 'nope'"):
        sweep_report(repo, "nope")


def test_cli_sweep_dry_run_and_errors(tmp_path: Path) -> None:
    from app.cli import app as cli

    spec = tmp_path / "s.toml"
    spec.write_text('name = "x"\nparticipants = 2\n[grid]\ndeadline_s = [0.1, 0.2, 0.3]\n')
    r = CliRunner().invoke(cli, ["sweep", str(spec), "--dry-run"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["trials"] == 3 * 2 * 2
    spec.write_text('name = "x"\n[grid]\nframe_period_s = [0]\n')
    r = CliRunner().invoke(cli, ["sweep", str(spec), "--dry-run"])
    assert r.exit_code == 2 and "frame_period_s" in r.output


def test_the_example_spec_is_valid() -> None:
    from app.study.sweep import load_spec

    spec = load_spec(Path(__file__).parents[3] / "examples" / "sweep_deadline.toml")
    assert len(plan_sweep(spec)) == 3 * 10 * 2
