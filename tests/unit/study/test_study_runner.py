"""Headless study runner: seeds, counterbalancing, storage, worker processes, the runtime adapter, the CLI.

The real trials come from ``app.control.runtime.run_headless_trial`` (the supervisor's part); these tests
replace it with fakes that return TrialResult-like objects, so they check the runner alone.
"""

from __future__ import annotations

import json
import sys
import types
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from app.config import Settings
from app.control.metrics import TrialEvent, TrialMetrics
from app.study import runner
from app.study.db import make_engine, upgrade_to_head
from app.study.repository import RecordedFrames, StudyRepository
from app.study.runner import (
    TrialJob,
    TrialOutcome,
    frames_from_result,
    participant_code,
    participant_seeds,
    run_study,
    run_trial_job,
)


def fake_metrics(method: str, participant_seed: int) -> TrialMetrics:
    """Deterministic metrics: the proactive method completes 3 more tasks than the reactive one."""
    base = 10 + participant_seed % 5
    return TrialMetrics(
        method=method,  # type: ignore[arg-type]
        duration_s=5.0,
        completed_tasks=base + (3 if method == "proactive" else 0),
        stop_replans=2 if method == "proactive" else 5,
        online_replans=8 if method == "proactive" else 2,
        avg_planning_time_s=0.1 + (participant_seed % 7) / 100,
        min_separation_m=0.3 + (participant_seed % 3) / 10,
    )


def fake_trial(job: TrialJob) -> TrialOutcome:
    """A picklable stand-in for run_trial_job (used inline and in worker processes)."""
    if job.participant_code.endswith("p03") and job.method == "reactive":
        return TrialOutcome(job.trial_id, None, error="RuntimeError: simulated crash")
    ended_early = job.participant_code.endswith("p04") and job.method == "reactive"
    n = 45
    frames = RecordedFrames(
        t=np.arange(n) / 30.0, q=np.full((n, 6), job.trial_seed % 3, float), skeleton=None
    )
    return TrialOutcome(
        trial_id=job.trial_id,
        metrics=asdict(fake_metrics(job.method, job.participant_seed)),
        events=[
            TrialEvent(t=0.0, kind="trial_started", payload={"method": job.method, "seed": job.trial_seed})
        ],
        frames=frames if job.record_frames else None,
        status="aborted" if ended_early else "completed",
        reason="robot_fault" if ended_early else "duration",
    )


@dataclass
class FakeTrialResult:
    metrics: TrialMetrics
    events: list[TrialEvent]
    frames: Any
    status: str = "completed"
    reason: str = "duration"


@pytest.fixture
def db(tmp_path: Path) -> Iterator[tuple[str, StudyRepository]]:
    url = f"sqlite:///{tmp_path / 'study.db'}"
    upgrade_to_head(url)
    repo = StudyRepository(make_engine(url))
    yield url, repo
    repo.close()


def test_participant_seeds_are_deterministic_and_do_not_depend_on_n() -> None:
    assert participant_seeds(7, 5) == participant_seeds(7, 5)
    assert participant_seeds(7, 10)[:5] == participant_seeds(7, 5)
    assert participant_seeds(8, 5) != participant_seeds(7, 5)
    assert len({p for p, _ in participant_seeds(7, 50)}) == 50
    assert participant_code(7, 0) == "sim-s7-p01"


def test_frames_from_result_accepts_arrays_or_per_frame_records() -> None:
    assert frames_from_result(None) is None and frames_from_result([]) is None
    f = frames_from_result({"t": [0.0, 0.1], "q": np.zeros((2, 6)), "skeleton": np.ones((2, 19, 3))})
    assert f is not None and f.skeleton is not None and f.skeleton.shape == (2, 1, 19, 3)  # one body, id 0
    assert f.body_ids is not None and f.body_ids.tolist() == [[0], [0]]
    per_frame = [
        types.SimpleNamespace(t=0.0, q=np.zeros(6), skeleton=None),
        types.SimpleNamespace(t=1 / 30, q=np.ones(6), skeleton=np.ones((19, 3))),
    ]
    g = frames_from_result(per_frame)
    assert g is not None and g.q.shape == (2, 6) and g.skeleton is not None
    assert np.isnan(g.skeleton[0]).all() and (g.skeleton[1] == 1).all()
    assert g.body_ids is not None and g.body_ids.tolist() == [[-1], [0]]  # nobody seen, then body 0
    with pytest.raises(ValueError, match=r"\(T, 6\)"):
        frames_from_result({"t": [0.0], "q": np.zeros((1, 5))})


def _check_study(repo: StudyRepository, session_id: int, n: int) -> None:
    trials = repo.list_trials(session_id=session_id)
    assert len(trials) == 2 * n
    by_participant: dict[str, list[Any]] = {}
    for t in trials:
        by_participant.setdefault(t.participant_code, []).append(t)
    firsts = []
    for code, ts in by_participant.items():
        ts.sort(key=lambda t: t.order_index)
        assert [t.order_index for t in ts] == [0, 1] and {t.method for t in ts} == {"proactive", "reactive"}
        assert ts[0].seed == ts[1].seed  # same trial seed for both methods
        assert ts[0].settings["participant_seed"] == ts[1].settings["participant_seed"]
        assert "api_token" not in ts[0].settings
        firsts.append(ts[0].method)
        for t in ts:
            if code.endswith("p03") and t.method == "reactive":
                assert t.status == "aborted" and "simulated crash" in (t.abort_reason or "")
                assert t.metrics is None
            elif code.endswith("p04") and t.method == "reactive":  # ended early by the runtime: kept
                assert t.status == "aborted" and "robot_fault" in (t.abort_reason or "")
                assert t.metrics is not None and repo.count_events(t.id) == 1
            else:
                assert t.status == "completed" and t.metrics is not None
                assert (
                    t.metrics.completed_tasks
                    == fake_metrics(t.method, t.settings["participant_seed"]).completed_tasks
                )
                assert repo.count_events(t.id) == 1
                frames = repo.load_frames(t.id)
                assert frames is not None and len(frames) == 45
    assert firsts.count("proactive") == firsts.count("reactive") == n // 2  # counterbalanced


def test_inline_study_is_counterbalanced_and_stored(db: tuple[str, StudyRepository]) -> None:
    _, repo = db
    settings = Settings(api_token="secret-token")
    result = run_study(
        participants=4,
        duration_s=5.0,
        seed=7,
        repo=repo,
        settings=settings,
        max_workers=0,
        progress=False,
        trial_fn=fake_trial,
    )
    assert (result.completed, result.aborted, len(result.trial_ids)) == (6, 2, 8)
    _check_study(repo, result.session_id, 4)
    again = run_study(
        participants=4,
        duration_s=5.0,
        seed=7,
        repo=repo,
        settings=settings,
        max_workers=0,
        progress=False,
        trial_fn=fake_trial,
    )
    assert again.participant_ids == result.participant_ids  # same seed: the same simulated people
    assert again.session_id != result.session_id


@pytest.mark.parametrize("engine", ["process", "ray"])
def test_study_in_worker_processes_and_as_ray_tasks(db: tuple[str, StudyRepository], engine: str) -> None:
    _, repo = db
    result = run_study(
        participants=4,
        duration_s=5.0,
        seed=11,
        repo=repo,
        settings=Settings(),
        max_workers=2,
        progress=False,
        trial_fn=fake_trial,
        engine=engine,
    )
    assert (result.completed, result.aborted) == (6, 2)
    _check_study(repo, result.session_id, 4)


def test_an_unknown_engine_is_refused_with_the_choices(db: tuple[str, StudyRepository]) -> None:
    with pytest.raises(ValueError, match=r"unknown engine 'dask'.*inline, process, ray"):
        runner.make_executor("dask", 2)


def test_run_trial_job_calls_the_runtime_contract(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[dict[str, Any]] = []

    def run_headless_trial(**kwargs: Any) -> FakeTrialResult:
        calls.append(kwargs)
        n = 30
        frames = [
            types.SimpleNamespace(t=i / 30, q=np.zeros(6), skeleton=np.zeros((19, 3)) if i else None)
            for i in range(n)
        ]
        return FakeTrialResult(
            metrics=fake_metrics(kwargs["method"], kwargs["participant_seed"]),
            events=[TrialEvent(t=0.5, kind="task_completed", payload={"station": "d1", "index": 0})],
            frames=frames,
        )

    fake_runtime = types.ModuleType("app.control.runtime")
    fake_runtime.run_headless_trial = run_headless_trial  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "app.control.runtime", fake_runtime)
    job = TrialJob(
        trial_id=5,
        participant_code="sim-s1-p01",
        participant_seed=123,
        trial_seed=456,
        method="reactive",
        order_index=1,
        duration_s=12.5,
        settings=Settings(deadline_s=0.2).model_dump(mode="json"),
    )
    out = run_trial_job(job)
    assert out.error is None and out.trial_id == 5
    (kw,) = calls
    assert kw["method"] == "reactive" and kw["duration_s"] == 12.5 and kw["source"] == "sim"
    assert (kw["seed"], kw["participant_seed"]) == (456, 123)
    assert isinstance(kw["settings"], Settings) and kw["settings"].deadline_s == 0.2
    assert (
        out.metrics is not None
        and out.metrics["completed_tasks"] == fake_metrics("reactive", 123).completed_tasks
    )
    assert out.frames is not None and len(out.frames) == 30 and out.frames.skeleton is not None

    def broken(**kwargs: Any) -> FakeTrialResult:
        raise RuntimeError("planner exploded")

    def faulted(**kwargs: Any) -> FakeTrialResult:
        return FakeTrialResult(fake_metrics("reactive", 1), [], None, status="aborted", reason="robot_fault")

    fake_runtime.run_headless_trial = faulted  # type: ignore[attr-defined]
    early = run_trial_job(job)
    assert (early.status, early.reason, early.error) == ("aborted", "robot_fault", None)
    assert early.metrics is not None and early.frames is None

    fake_runtime.run_headless_trial = broken  # type: ignore[attr-defined]
    failed = run_trial_job(job)
    assert failed.metrics is None and failed.error is not None and "planner exploded" in failed.error


def test_cli_study_report_export(
    db: tuple[str, StudyRepository], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from app.cli import app as cli

    url, _ = db
    monkeypatch.setattr(runner, "run_trial_job", fake_trial)
    monkeypatch.setenv("HRC_DATA_DIR", str(tmp_path / "data"))
    cli_runner = CliRunner()
    r = cli_runner.invoke(cli, ["db", "upgrade", "--url", url])
    assert r.exit_code == 0, r.output
    args = ["--participants", "4", "--duration", "5", "--seed", "3", "--workers", "0", "--no-progress"]
    r = cli_runner.invoke(cli, ["study", *args, "--url", url])
    assert r.exit_code == 0, r.output
    session_id = json.loads(r.stdout.splitlines()[0])["session_id"]
    r = cli_runner.invoke(cli, ["report", "--json", "--url", url])
    assert r.exit_code == 0, r.output
    report = json.loads(r.stdout)
    # p03 and p04 have no completed reactive trial: two pairs are left
    assert report["session_id"] == session_id and report["n_participants"] == 2
    for method in ("proactive", "reactive"):
        for metric in (
            "completed_tasks",
            "avg_planning_time_s",
            "stop_replans_per_task",
            "online_replans_per_task",
        ):
            assert set(report[method][metric]) >= {"mean", "sd"}
    assert report["proactive"]["completed_tasks"]["mean"] - report["reactive"]["completed_tasks"][
        "mean"
    ] == pytest.approx(3.0, abs=1.0)
    assert set(report["p_values"]) >= {"completed_tasks", "online_replans_per_task"}
    r = cli_runner.invoke(cli, ["report", "--url", url, "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "rep" / "boxplots.png").is_file() and "| proactive |" in r.stdout
    r = cli_runner.invoke(cli, ["report", "--json", "--url", url, "--session", "999"])
    assert r.exit_code != 0 and "999" in r.output
    r = cli_runner.invoke(cli, ["export", "--out", str(tmp_path / "csv"), "--url", url])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "csv").iterdir()) == [
        "events.csv",
        "metrics.csv",
        "participants.csv",
        "trials.csv",
    ]


def interrupting_trial(job: TrialJob) -> TrialOutcome:
    if job.participant_code.endswith("p02"):
        raise KeyboardInterrupt
    return fake_trial(job)


def test_an_interrupted_study_leaves_no_running_trials(db: tuple[str, StudyRepository]) -> None:
    _, repo = db
    with pytest.raises(KeyboardInterrupt):
        run_study(
            participants=2,
            duration_s=5.0,
            seed=1,
            repo=repo,
            settings=Settings(),
            max_workers=0,
            progress=False,
            trial_fn=interrupting_trial,
        )
    trials = repo.list_trials()
    assert len(trials) == 4 and not [t for t in trials if t.status == "running"]
    interrupted = [t for t in trials if t.status == "aborted"]
    assert interrupted and all("interrupted" in (t.abort_reason or "") for t in interrupted)


def test_the_longer_proactive_trials_are_started_first(db: tuple[str, StudyRepository]) -> None:
    _, repo = db
    settings = Settings(api_token="secret-token")
    started: list[str] = []

    def recording_trial(job: TrialJob) -> TrialOutcome:
        started.append(job.method)
        return fake_trial(job)

    run_study(
        participants=3,
        duration_s=5.0,
        seed=7,
        repo=repo,
        settings=settings,
        max_workers=0,
        progress=False,
        trial_fn=recording_trial,
    )
    assert started == ["proactive"] * 3 + ["reactive"] * 3
