"""``hrc tune``: the spec's rules (no safety parameter, only the tuning seeds, no unknown key), the objective,
and a real tiny search through a local Ray Tune whose best settings load as settings and run a study."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from app.config import Settings, SettingsFileError, load_settings_file
from app.study.runner import TrialOutcome
from app.study.tune import (
    INFEASIBLE_PENALTY,
    TuneSpecError,
    load_tune_spec,
    parse_tune_spec,
    run_tune,
    score_outcomes,
)

ROOT = Path(__file__).resolve().parents[2]


def _spec(**changes: Any) -> dict[str, Any]:
    spec: dict[str, Any] = {
        "name": "t",
        "seeds": {"first": 1000, "last": 1000},
        "duration_s": 15.0,
        "methods": ["reactive"],
        "num_samples": 2,
        "concurrency": 1,
        "space": {"deadline_s": {"low": 0.05, "high": 0.2}},
    }
    spec.update(changes)
    return spec


def test_the_example_spec_is_valid() -> None:
    spec = load_tune_spec(ROOT / "examples" / "tune_margins.toml")
    assert spec.seeds == [1000, 1001, 1002, 1003]
    assert {p.name for p in spec.space} == {"deadline_s", "fetch_reaction_s", "anticipate_fetch"}


@pytest.mark.parametrize(
    "key",
    [
        "frame_period_s",  # a Settings field: the tracker's camera
        "camera_pose",
        "v_human_mps",  # SSMParams
        "t_stop_s",
        "intrusion_m",
        "human_speed_max_mps",  # the speed governor
        "tracking_margin_m",
        "tracker_latency_s",  # any tracker, SSM or stopping-model setting, also one added later
        "ssm_t_reaction_s",
        "stopping_model",
    ],
)
def test_safety_parameters_are_refused(key: str) -> None:
    with pytest.raises(TuneSpecError, match=rf"\[space\] {key} \(.*\) is an ISO/TS 15066 .*never tuned"):
        parse_tune_spec(
            _spec(space={"deadline_s": {"low": 0.05, "high": 0.2}, key: {"low": 0.1, "high": 0.2}})
        )


@pytest.mark.parametrize("first,last", [(999, 1003), (1998, 2000), (1, 3), (2000, 2001)])
def test_seeds_outside_the_tuning_seeds_are_refused(first: int, last: int) -> None:
    with pytest.raises(TuneSpecError, match=rf"`seeds` {first}-{last} leave the tuning seeds 1000-1999"):
        parse_tune_spec(_spec(seeds={"first": first, "last": last}))


@pytest.mark.parametrize(
    "changes,named",
    [
        ({"participants": 3}, "unknown spec key participants"),
        ({"space": {"deadline": {"low": 0.05, "high": 0.2}}}, r"\[space\] deadline: unknown key"),
        ({"space": {"deadline_s": {"lo": 0.05, "high": 0.2}}}, r"\[space\] deadline_s: unknown key lo"),
        ({"space": {"deadline_s": {"choices": [0.1], "log": True}}}, "unknown key log beside `choices`"),
        ({"seeds": {"first": 1000, "count": 3}}, "`seeds` must be"),
    ],
)
def test_unknown_keys_are_refused_by_name(changes: dict[str, Any], named: str) -> None:
    with pytest.raises(TuneSpecError, match=named):
        parse_tune_spec(_spec(**changes))


@pytest.mark.parametrize(
    "space,why",
    [
        ({"population": {"choices": ["x.toml"]}}, "not a planner or forecast parameter"),
        ({"host": {"choices": ["0.0.0.0"]}}, "not a planner or forecast parameter"),
        ({"method": {"choices": ["reactive"]}}, "the methods come from `methods`"),
        ({"deadline_s": {"low": 0.05, "high": 5.0}}, r"deadline_s: 5.0 is not a valid value: .*less than"),
        ({"deadline_s": {"low": 0.2, "high": 0.1}}, "must be below"),
        ({"planner_workers": {"low": 1.5, "high": 8}}, "`low` must be an integer"),
        ({"anticipate_fetch": {"low": 0, "high": 1}}, "not a number; give"),
        ({}, r"needs a \[space\]"),
    ],
)
def test_untunable_settings_and_bad_ranges_are_refused(space: dict[str, Any], why: str) -> None:
    with pytest.raises(TuneSpecError, match=why):
        parse_tune_spec(_spec(space=space))


def _outcome(tasks: int, violations: int = 0, **extra: Any) -> TrialOutcome:
    metrics = {"completed_tasks": tasks, "violations": violations, **extra}
    return TrialOutcome(0, metrics)


def test_the_objective_is_mean_tasks_when_safe_and_a_penalty_otherwise() -> None:
    assert score_outcomes([_outcome(4), _outcome(2)])["score"] == 3.0
    violated = score_outcomes([_outcome(9, violations=2), _outcome(9)])
    assert not violated["feasible"] and violated["score"] == -2 * INFEASIBLE_PENALTY
    touched = score_outcomes([_outcome(9, harmful_contacts=1, contacts=1), _outcome(9)])
    assert not touched["feasible"] and touched["score"] == -INFEASIBLE_PENALTY
    # a contact within the power and force limits is the safety model's, not a fault of the sample
    permitted = score_outcomes([_outcome(9, harmful_contacts=0, contacts=2), _outcome(9)])
    assert permitted["feasible"] and permitted["score"] == 9.0
    broken = score_outcomes([_outcome(9), TrialOutcome(1, None, error="boom")])
    assert not broken["feasible"] and broken["failed"] == 1 and broken["score"] == -INFEASIBLE_PENALTY


def test_a_settings_file_names_unknown_keys_and_bad_values(tmp_path: Path) -> None:
    good = tmp_path / "good.toml"
    good.write_text("# a comment\ndeadline_s = 0.12\nanticipate_fetch = false\n")
    assert Settings(**load_settings_file(good)).deadline_s == 0.12
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("deadline_s = 0.12\nplan_speed = 2\n")
    with pytest.raises(SettingsFileError, match="plan_speed is not a setting"):
        load_settings_file(unknown)
    bad = tmp_path / "bad.toml"
    bad.write_text("deadline_s = 7.0\n")
    with pytest.raises(SettingsFileError, match="deadline_s: Input should be less than or equal to 2"):
        load_settings_file(bad)


def test_an_inline_search_runs_real_trials_and_keeps_the_best_feasible_sample() -> None:
    spec = parse_tune_spec(_spec())
    result = run_tune(spec, engine="inline")
    assert len(result.samples) == 2
    for row in result.samples:
        assert row["feasible"] and row["violations"] == 0 and row["failed"] == 0
        assert 0.05 <= row["params"]["deadline_s"] <= 0.2
    assert result.best is not None
    assert result.best["score"] == max(r["score"] for r in result.samples)


def _hrc(*args: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "app.cli", *args],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


@pytest.mark.slow
def test_a_ray_tune_search_writes_settings_that_hrc_study_accepts(tmp_path: Path) -> None:
    spec = tmp_path / "tiny.toml"
    spec.write_text(
        'name = "tiny"\nseeds = { first = 1000, last = 1000 }\nduration_s = 15.0\nmethods = ["reactive"]\n'
        "num_samples = 2\nconcurrency = 1\n[space]\ndeadline_s = { low = 0.05, high = 0.2 }\n"
    )
    out = tmp_path / "best.toml"
    env = {**os.environ, "HRC_DATA_DIR": str(tmp_path / "data")}
    run = _hrc("tune", str(spec), "--json", "--out", str(out), env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout)  # --json: one JSON object on stdout, Ray's output on stderr
    assert result["engine"] == "ray" and len(result["trials"]) == 2
    assert all(t["feasible"] and t["violations"] == 0 for t in result["trials"])
    assert result["best_score"] == max(t["score"] for t in result["trials"])
    assert result["out"] == str(out)

    text = out.read_text()
    assert "seeds: 1000-1000" in text and "score:" in text  # the comment header
    assert tomllib.loads(text) == result["best_params"]  # only the tuned keys
    settings = Settings(**load_settings_file(out))
    assert settings.deadline_s == result["best_params"]["deadline_s"]

    url = f"sqlite:///{(tmp_path / 'study.db').as_posix()}"
    study = _hrc(
        "study",
        "--settings",
        str(out),
        "--participants",
        "1",
        "--duration",
        "1",
        "--engine",
        "inline",
        "--no-frames",
        "--no-progress",
        "--url",
        url,
        env=env,
    )
    assert study.returncode == 0, study.stderr[-3000:]
    assert json.loads(study.stdout.splitlines()[-1])["completed"] == 2
    with sqlite3.connect(tmp_path / "study.db") as db:  # the study ran with the tuned settings
        stored = [json.loads(row[0])["deadline_s"] for row in db.execute("SELECT settings FROM trials")]
    assert stored == [settings.deadline_s] * 2
