"""Sweeps that survive their driver: SIGKILL midway and a restart (real trials on a local Ray), and two
drivers writing one sweep into the real PostgreSQL server at once (nothing lost, nothing twice)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import pytest
from sqlalchemy import text

from app.control.metrics import TrialEvent, TrialMetrics
from app.study.db import make_engine, upgrade_to_head
from app.study.repository import StudyRepository
from app.study.runner import TrialJob, TrialOutcome
from app.study.sweep import parse_spec, plan_sweep, run_sweep, sweep_report

ROOT = Path(__file__).resolve().parents[2]
SPEC = 'name = "kill"\nparticipants = 2\nduration_s = 4.0\nseed = 5\n[grid]\ndeadline_s = [0.1, 0.2]\n'


def _stored(url: str, prefix: str) -> list[str]:
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            q = text("SELECT trial_key FROM trials WHERE trial_key LIKE :p ORDER BY trial_key")
            return [r[0] for r in conn.execute(q, {"p": prefix + "%"})]
    finally:
        engine.dispose()


def _sweep_cmd(spec: Path, url: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "app.cli",
        "sweep",
        str(spec),
        "--workers",
        "2",
        "--no-progress",
        "--url",
        url,
    ]


@pytest.mark.slow
def test_a_sweep_killed_with_sigkill_resumes_and_stores_every_trial_once(tmp_path: Path) -> None:
    spec = tmp_path / "kill.toml"
    spec.write_text(SPEC)
    url = f"sqlite:///{(tmp_path / 'study.db').as_posix()}"
    upgrade_to_head(url)
    env = {**os.environ, "HRC_DATA_DIR": str(tmp_path / "data")}
    first = subprocess.Popen(
        _sweep_cmd(spec, url),
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 400
        while not _stored(url, "kill|"):
            assert first.poll() is None, "the sweep ended before it stored a trial"
            assert time.monotonic() < deadline, "no trial stored within 400 s"
            time.sleep(0.5)
        os.kill(first.pid, signal.SIGKILL)
        first.wait(timeout=30)
    finally:
        with contextlib.suppress(ProcessLookupError):  # the driver's local Ray processes (its session)
            os.killpg(first.pid, signal.SIGKILL)
    at_kill = _stored(url, "kill|")
    assert 1 <= len(at_kill) < 8, f"the kill came too late to test the resume: {len(at_kill)} stored"

    second = subprocess.run(
        _sweep_cmd(spec, url), cwd=ROOT, env=env, capture_output=True, text=True, timeout=500
    )
    assert second.returncode == 0, second.stderr[-3000:]
    result = json.loads(second.stdout.strip().splitlines()[-1])
    assert result["planned"] == 8 and result["skipped"] == len(at_kill)
    assert result["completed"] == 8 - len(at_kill) and result["failed"] == 0

    keys = _stored(url, "kill|")
    expected = {
        t.key
        for t in plan_sweep(
            parse_spec(
                {
                    "name": "kill",
                    "participants": 2,
                    "duration_s": 4.0,
                    "seed": 5,
                    "grid": {"deadline_s": [0.1, 0.2]},
                }
            )
        )
    }
    assert sorted(keys) == sorted(expected)  # every trial, each once
    repo = StudyRepository(make_engine(url))
    try:
        rows = [r for r in repo.metrics_rows(status="completed")]
        assert len(rows) == 8
        report = sweep_report(repo, "kill")
    finally:
        repo.close()
    assert list(report["settings"]) == ["deadline_s=0.1", "deadline_s=0.2"]
    assert all(s["n_participants"] == 2 for s in report["settings"].values())
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "app.cli",
            "report",
            "--sweep",
            "kill",
            "--out",
            str(tmp_path / "rep"),
            "--url",
            url,
        ],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "rep" / "effect_deadline_s.png").stat().st_size > 0
    assert (tmp_path / "rep" / "sweep.csv").read_text().count("deadline_s=0.2") > 0


_barrier = threading.Barrier(2)


def _racing_trial(job: TrialJob) -> TrialOutcome:
    """A fake trial; both drivers meet at their first trial, after each has planned the whole sweep."""
    if job.trial_id == 0:
        _barrier.wait(timeout=60)
    time.sleep(0.01 * (job.trial_id % 3))
    metrics = TrialMetrics(
        method=job.method,  # type: ignore[arg-type]
        duration_s=4.0,
        completed_tasks=5 + job.participant_seed % 3 + (2 if job.method == "proactive" else 0),
        stop_replans=1,
        online_replans=1,
        avg_planning_time_s=0.1,
        min_separation_m=0.5,
    )
    events = [TrialEvent(t=float(i), kind="state_changed", payload={"i": i}) for i in range(3)]
    return TrialOutcome(job.trial_id, asdict(metrics), events=events)


@pytest.mark.postgres
def test_two_drivers_writing_one_sweep_into_postgresql_store_each_trial_once(postgres_server) -> None:
    url = postgres_server.create_database()
    upgrade_to_head(url)
    spec = parse_spec(
        {
            "name": "race",
            "participants": 4,
            "duration_s": 4.0,
            "seed": 9,
            "grid": {"deadline_s": [0.1, 0.2, 0.3]},
        }
    )
    results: list = [None, None]
    errors: list[BaseException] = []

    def drive(i: int) -> None:
        repo = StudyRepository(make_engine(url))
        try:
            results[i] = run_sweep(
                spec, repo, engine="inline", workers=0, progress=False, trial_fn=_racing_trial
            )
        except BaseException as exc:
            errors.append(exc)
            _barrier.abort()
        finally:
            repo.close()

    threads = [threading.Thread(target=drive, args=(i,)) for i in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    assert not errors, errors
    a, b = results
    assert a.skipped == b.skipped == 0  # both planned all 24 trials: a real race
    assert a.completed + b.completed == 24
    assert a.duplicates + b.duplicates == 24  # every trial the loser stored was refused by the key
    engine = make_engine(url)
    try:
        with engine.connect() as conn:
            keys = [
                r[0] for r in conn.execute(text("SELECT trial_key FROM trials WHERE trial_key IS NOT NULL"))
            ]
            n_metrics = conn.execute(text("SELECT count(*) FROM trial_metrics")).scalar_one()
            n_events = conn.execute(text("SELECT count(*) FROM trial_events")).scalar_one()
            n_trials = conn.execute(text("SELECT count(*) FROM trials")).scalar_one()
    finally:
        engine.dispose()
    assert sorted(keys) == sorted(t.key for t in plan_sweep(spec))
    assert n_trials == n_metrics == 24  # no trial row or metrics left behind by a refused store
    assert n_events == 24 * 3
