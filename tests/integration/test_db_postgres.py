"""The study database on SQLite and on a real PostgreSQL server: migrations agree with the models, and the
repository round-trips every record type with the same behaviour on both backends."""

from __future__ import annotations

import io
import math
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pandas as pd
import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from app.control.metrics import TrialEvent, TrialMetrics
from app.study.db import current_revision, make_engine, upgrade_to_head
from app.study.export import DATE_COLUMNS, events_csv, metrics_csv, trials_csv
from app.study.models import Base
from app.study.repository import (
    ConflictError,
    NotFoundError,
    RecordedFrames,
    StudyRepository,
    TrialStateError,
)
from app.study.schemas import ParticipantCreate, ParticipantUpdate, StudySessionCreate, StudySessionUpdate
from app.study.stats import summarize

HEAD = "0009"


@pytest.fixture
def repo(db_url: str) -> Iterator[StudyRepository]:
    upgrade_to_head(db_url)
    r = StudyRepository(make_engine(db_url))
    yield r
    r.close()


def _metrics(method: str, **kw: float) -> TrialMetrics:
    return TrialMetrics(method=method, duration_s=60.0, **kw)  # type: ignore[arg-type]


def test_migrations_match_models(db_url: str) -> None:
    upgrade_to_head(db_url)
    engine = make_engine(db_url)
    try:
        with engine.connect() as conn:
            diff = compare_metadata(
                MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata
            )
        assert diff == []
        assert current_revision(engine) == HEAD
        assert set(inspect(engine).get_table_names()) >= set(Base.metadata.tables)
    finally:
        engine.dispose()
    upgrade_to_head(db_url)  # idempotent at head


def test_participant_crud_and_conflicts(repo: StudyRepository) -> None:
    p = repo.create_participant(
        ParticipantCreate(code="P01", age=27, sex="f", experience="none", notes="ünïcode")
    )
    assert p.id > 0 and p.created.tzinfo is not None and p.notes == "ünïcode"
    with pytest.raises(ConflictError, match="P01"):
        repo.create_participant(ParticipantCreate(code="P01"))
    q = repo.create_participant(ParticipantCreate(code="P02"))
    with pytest.raises(ConflictError):
        repo.update_participant(q.id, ParticipantUpdate(code="P01"))
    updated = repo.update_participant(p.id, ParticipantUpdate(age=28))
    assert (updated.age, updated.sex, updated.code) == (28, "f", "P01")
    assert [x.code for x in repo.list_participants()] == ["P01", "P02"]
    assert repo.get_participant_by_code("P02") == repo.get_participant(q.id)
    with pytest.raises(NotFoundError):
        repo.get_participant(9999)
    repo.create_trial(participant_id=q.id, method="reactive")
    with pytest.raises(ConflictError, match="trials"):
        repo.delete_participant(q.id)
    repo.delete_participant(q.id, with_trials=True)
    assert repo.list_trials() == []
    assert repo.get_participant_by_code("P02") is None


def test_sessions_and_trial_lifecycle(repo: StudyRepository) -> None:
    s = repo.create_session(StudySessionCreate(name="day 1"))
    assert repo.update_session(s.id, StudySessionUpdate(notes="calm")).notes == "calm"
    assert repo.latest_session() == repo.get_session(s.id)
    p = repo.create_participant(ParticipantCreate(code="A"))
    t0 = repo.create_trial(
        participant_id=p.id, method="proactive", session_id=s.id, seed=2**40, settings={"x": 1}
    )
    t1 = repo.create_trial(participant_id=p.id, method="reactive", session_id=s.id)
    assert (t0.order_index, t1.order_index, t0.status, t0.seed) == (0, 1, "running", 2**40)
    assert t0.metrics is None and t0.participant_code == "A"
    with pytest.raises(NotFoundError):
        repo.create_trial(participant_id=p.id, method="reactive", session_id=999)
    with pytest.raises(ValueError, match="reactive"):
        repo.finish_trial(t0.id, status="completed", metrics=_metrics("reactive"))
    done = repo.finish_trial(
        t0.id,
        status="completed",
        metrics=_metrics(
            "proactive",
            completed_tasks=4,
            stop_replans=2,
            online_replans=6,
            budget_moving_scaled_s=41.5,
            budget_stopped_s=18.5,
            budget_waiting_for_person_s=7.25,
            stop_replans_moving=1,
        ),
        events=[TrialEvent(t=1.0, kind="task_completed", payload={"station": "d1", "index": 0})],
    )
    assert done.status == "completed" and done.ended_at is not None and done.ended_at >= done.started_at
    assert done.metrics is not None and done.metrics.completed_tasks == 4
    assert done.metrics.min_separation_m is None  # inf: no person seen
    assert done.metrics.stop_replans_per_task == 0.5 and done.metrics.online_replans_per_task == 1.5
    # the time budget is stored; a trial without arrivals has no arrival error (NULL, not 0)
    assert (done.metrics.budget_moving_scaled_s, done.metrics.budget_stopped_s) == (41.5, 18.5)
    assert done.metrics.budget_waiting_for_person_s == 7.25 and done.metrics.stop_replans_moving == 1
    assert done.metrics.arrivals == 0 and done.metrics.arrival_error_median_abs_s is None
    with pytest.raises(TrialStateError):
        repo.finish_trial(t0.id, status="aborted")
    assert [t.id for t in repo.list_trials(status="running")] == [t1.id]
    assert [t.id for t in repo.list_trials(method="proactive", session_id=s.id)] == [t0.id]
    repo.delete_session(s.id)
    assert repo.get_trial(t1.id).session_id is None


def test_abort_interrupted_and_method_order(repo: StudyRepository) -> None:
    ps = [repo.create_participant(ParticipantCreate(code=f"P{i}")) for i in range(4)]
    orders = [repo.suggest_method_order(p.id) for p in ps]
    assert orders[0] == orders[2] == ["proactive", "reactive"]
    assert orders[1] == orders[3] == ["reactive", "proactive"]
    running = repo.create_trial(participant_id=ps[0].id, method="proactive")
    finished = repo.create_trial(participant_id=ps[0].id, method="reactive")
    repo.finish_trial(finished.id, status="completed", metrics=_metrics("reactive"))
    assert repo.abort_interrupted_trials() == [running.id]
    t = repo.get_trial(running.id)
    assert t.status == "aborted" and t.abort_reason and "interrupted" in t.abort_reason
    assert repo.get_trial(finished.id).status == "completed"
    assert repo.abort_interrupted_trials() == []


def test_events_frames_and_json_payloads(repo: StudyRepository) -> None:
    p = repo.create_participant(ParticipantCreate(code="F"))
    t = repo.create_trial(participant_id=p.id, method="proactive")
    events = [
        TrialEvent(
            t=0.5, kind="violation", payload={"separation_m": np.float32(0.25), "required_m": math.inf}
        ),
        TrialEvent(t=0.1, kind="state_changed", payload={"from": "nominal", "to": "avoid"}),
    ]
    with repo.event_writer(t.id) as w:
        w.write_many(events)
    got = repo.list_events(t.id)
    assert [e.kind for e in got] == ["state_changed", "violation"]  # time order
    assert got[1].payload == {"separation_m": 0.25, "required_m": None}
    assert repo.count_events(t.id, kind="violation") == 1
    rng = np.random.default_rng(0)
    n = 701
    frames = RecordedFrames(
        t=np.arange(n) / 30.0, q=rng.normal(size=(n, 6)), skeleton=rng.normal(size=(n, 19, 3))
    )
    assert repo.save_frames(t.id, frames, chunk_frames=300) == 3
    back = repo.load_frames(t.id)
    assert back is not None and len(back) == n
    np.testing.assert_array_equal(back.t, frames.t)
    np.testing.assert_array_equal(back.q, frames.q.astype(np.float32))
    np.testing.assert_array_equal(back.skeleton, frames.skeleton.astype(np.float32))
    assert repo.load_frames(9999) is None
    repo.delete_trial(t.id)
    assert repo.count_events(t.id) == 0 and repo.load_frames(t.id) is None


def test_times_are_utc_and_exports_parse(repo: StudyRepository) -> None:
    p = repo.create_participant(ParticipantCreate(code="T"))
    start = datetime(2026, 5, 4, 11, 30, tzinfo=UTC) + timedelta(microseconds=123)
    t = repo.create_trial(participant_id=p.id, method="reactive", started_at=start)
    repo.finish_trial(t.id, status="completed", metrics=_metrics("reactive", completed_tasks=3))
    read = repo.get_trial(t.id)
    assert read.started_at == start and read.started_at.utcoffset() == timedelta(0)
    df = pd.read_csv(io.StringIO(trials_csv(repo)), parse_dates=list(DATE_COLUMNS["trials"]))
    assert df.loc[0, "started_at"] == pd.Timestamp(start)
    m = pd.read_csv(io.StringIO(metrics_csv(repo)))
    assert m.loc[0, "completed_tasks"] == 3 and m.loc[0, "participant_code"] == "T"
    assert pd.read_csv(io.StringIO(events_csv(repo))).empty


def test_summary_from_the_database(repo: StudyRepository) -> None:
    rng = np.random.default_rng(3)
    for i in range(6):
        p = repo.create_participant(ParticipantCreate(code=f"S{i}"))
        for method in repo.suggest_method_order(p.id):
            tasks = int(rng.integers(8, 14)) + (4 if method == "proactive" else 0)
            t = repo.create_trial(participant_id=p.id, method=method)  # type: ignore[arg-type]
            repo.finish_trial(t.id, status="completed", metrics=_metrics(method, completed_tasks=tasks))
    s = summarize(repo)
    assert s["n_participants"] == 6
    assert s["proactive"]["completed_tasks"]["mean"] > s["reactive"]["completed_tasks"]["mean"]
    assert s["p_values"]["completed_tasks"] is not None and s["p_values"]["completed_tasks"] < 0.05
