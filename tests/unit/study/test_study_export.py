"""CSV export: the files read back in pandas with the right dtypes and values."""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import pandas as pd
import pytest
from pandas.api import types as ptypes

from app.control.metrics import TrialEvent, TrialMetrics
from app.study.db import make_engine, upgrade_to_head
from app.study.export import (
    DATE_COLUMNS,
    EVENT_COLUMNS,
    METRICS_COLUMNS,
    PARTICIPANT_COLUMNS,
    TRIAL_COLUMNS,
    export_all,
    participants_csv,
    table_csv,
)
from app.study.models import METRIC_COLUMNS
from app.study.repository import StudyRepository
from app.study.schemas import ParticipantCreate, StudySessionCreate

NOTES = 'says "hi", then\nleaves — ünïcode'


@pytest.fixture
def repo(tmp_path: Path) -> Iterator[StudyRepository]:
    url = f"sqlite:///{tmp_path / 'x.db'}"
    upgrade_to_head(url)
    r = StudyRepository(make_engine(url))
    s1 = r.create_session(StudySessionCreate(name="day 1"))
    s2 = r.create_session(StudySessionCreate(name="day 2"))
    a = r.create_participant(ParticipantCreate(code="A01", age=25, sex="m", notes=NOTES))
    b = r.create_participant(ParticipantCreate(code="B02"))  # no age, sex, experience
    start = datetime(2026, 3, 2, 10, 0, 0, 250000, tzinfo=UTC)
    for p, session in ((a, s1), (b, s2)):
        for method in ("proactive", "reactive"):
            t = r.create_trial(
                participant_id=p.id, method=method, session_id=session.id, seed=3, started_at=start
            )
            r.finish_trial(
                t.id,
                status="completed",
                metrics=TrialMetrics(
                    method=method, duration_s=30.0, completed_tasks=5, avg_planning_time_s=0.125
                ),
                events=[
                    TrialEvent(t=0.0, kind="trial_started", payload={"method": method, "seed": 3}),
                    TrialEvent(t=1.25, kind="task_completed", payload={"station": "drop 1", "index": 0}),
                ],
            )
    r.create_trial(participant_id=b.id, method="proactive", session_id=s2.id)  # still running: no metrics
    yield r
    r.close()


def test_export_reads_back_in_pandas_with_the_right_dtypes(repo: StudyRepository, tmp_path: Path) -> None:
    paths = export_all(repo, tmp_path / "out")
    assert set(paths) == {"participants", "trials", "metrics", "events"}
    frames = {k: pd.read_csv(p, parse_dates=list(DATE_COLUMNS[k])) for k, p in paths.items()}
    par, tri, met, ev = frames["participants"], frames["trials"], frames["metrics"], frames["events"]
    assert tuple(par.columns) == PARTICIPANT_COLUMNS and tuple(tri.columns) == TRIAL_COLUMNS
    assert tuple(met.columns) == METRICS_COLUMNS and tuple(ev.columns) == EVENT_COLUMNS

    assert ptypes.is_integer_dtype(par["participant_id"]) and ptypes.is_string_dtype(par["code"])
    assert ptypes.is_float_dtype(par["age"]) and pd.isna(par.loc[1, "age"]) and par.loc[0, "age"] == 25
    assert par.loc[0, "notes"] == NOTES  # quotes, comma, newline and non-ASCII survive
    assert list(par["n_trials"]) == [2, 3]
    assert isinstance(par["created"].dtype, pd.DatetimeTZDtype) and str(par["created"].dt.tz) == "UTC"

    assert len(tri) == 5 and list(tri["status"]) == ["completed"] * 4 + ["running"]
    assert tri.loc[0, "started_at"] == pd.Timestamp("2026-03-02T10:00:00.25", tz="UTC")
    assert pd.isna(tri.loc[4, "ended_at"]) and isinstance(tri["ended_at"].dtype, pd.DatetimeTZDtype)
    assert ptypes.is_integer_dtype(tri["seed"]) and ptypes.is_integer_dtype(tri["order_index"])

    assert len(met) == 4  # one row per trial with metrics
    assert list(met["participant_code"]) == ["A01", "A01", "B02", "B02"]
    assert list(met["method"]) == ["proactive", "reactive"] * 2
    for c in METRIC_COLUMNS:
        kind = type(getattr(TrialMetrics(), c))
        check = ptypes.is_integer_dtype if kind is int else ptypes.is_float_dtype
        assert check(met[c]), (c, met[c].dtype)
    assert met["avg_planning_time_s"].eq(0.125).all() and met["min_separation_m"].isna().all()

    assert len(ev) == 8 and ptypes.is_float_dtype(ev["t"]) and ptypes.is_string_dtype(ev["kind"])
    assert ev.loc[1, "payload_json"] == '{"index": 0, "station": "drop 1"}'


def test_session_filter_and_text_helpers(repo: StudyRepository) -> None:
    day2 = repo.list_sessions()[1].id
    met = pd.read_csv(io.StringIO(table_csv(repo, "metrics", session_id=day2)))
    assert list(met["participant_code"]) == ["B02", "B02"]
    ev = pd.read_csv(io.StringIO(table_csv(repo, "events", trial_id=1)))
    assert set(ev["trial_id"]) == {1}
    assert participants_csv(repo).splitlines()[0] == ",".join(PARTICIPANT_COLUMNS)
    with pytest.raises(KeyError, match="unknown table"):
        table_csv(repo, "secrets")


def test_recorded_motion_exports_as_clips_the_predictor_reads(repo: StudyRepository, tmp_path: Path) -> None:
    import numpy as np

    from app.prediction.data import load_clip_dir
    from app.prediction.skeleton import NUM_JOINTS
    from app.study.export import export_clips
    from app.study.repository import RecordedFrames

    trials = repo.list_trials()
    n = 200
    t = np.arange(n) / 30.0
    t[120:] += 0.5  # the tracker stalled for half a second: a new piece
    sk = np.cumsum(np.full((n, NUM_JOINTS, 3), 0.001), axis=0)
    sk[60:62] = np.nan  # the person was lost for two frames: another cut
    repo.save_frames(trials[0].id, RecordedFrames(t=t, q=np.zeros((n, 6)), skeleton=sk))
    repo.save_frames(trials[1].id, RecordedFrames(t=t, q=np.zeros((n, 6)), skeleton=None))
    paths = export_clips(repo, tmp_path / "clips")
    assert [p.name for p in paths] == [f"trial{trials[0].id}_A01_{k}.npz" for k in (0, 1, 2)]
    clips = load_clip_dir(tmp_path / "clips")
    assert sorted(c.frames for c in clips) == [58, 60, 80]
    first = next(c for c in clips if c.name.endswith("_0"))
    np.testing.assert_allclose(first.positions, sk[:60], atol=1e-6)


def test_the_safety_models_keys_reach_the_metrics_csv_and_the_report_per_trial_and_method(
    tmp_path: Path,
) -> None:
    """ISO/TS 15066's judge with PFL (issue 36): violations apart from those a faster person started,
    harmful contacts and the time the person was faster than assumed, per trial in ``metrics.csv`` and per
    method in ``hrc report`` (its JSON and its CSV table)."""
    from app.study.stats import REPORT_METRICS, csv_table, summarize

    keys = ("violations_person_faster", "harmful_contacts", "exceedance_s")
    assert set(keys) <= set(REPORT_METRICS) and set(keys) <= set(METRIC_COLUMNS)
    url = f"sqlite:///{tmp_path / 'safety.db'}"
    upgrade_to_head(url)
    r = StudyRepository(make_engine(url))
    try:
        values = {"proactive": (2, 0, 0.5), "reactive": (0, 1, 1.25)}
        for code in ("P1", "P2"):
            p = r.create_participant(ParticipantCreate(code=code))
            for method, (faster, harmful, exceed) in values.items():
                t = r.create_trial(participant_id=p.id, method=method, seed=1)
                r.finish_trial(
                    t.id,
                    status="completed",
                    metrics=TrialMetrics(
                        method=method,
                        duration_s=30.0,
                        completed_tasks=3,
                        violations_person_faster=faster,
                        harmful_contacts=harmful,
                        exceedance_s=exceed,
                    ),
                    events=[],
                )
        met = pd.read_csv(io.StringIO(table_csv(r, "metrics")))
        for method, want in values.items():
            rows = met[met["method"] == method]
            assert len(rows) == 2
            for key, value in zip(keys, want, strict=True):
                assert rows[key].tolist() == [value, value], (method, key)
        summary = summarize(r.metrics_rows())
        json_report = json.loads(json.dumps(summary, allow_nan=False))  # `hrc report --json`
        for method, want in values.items():
            for key, value in zip(keys, want, strict=True):
                assert json_report[method][key]["mean"] == pytest.approx(value), (method, key)
        table = pd.read_csv(io.StringIO(csv_table(summary)))
        for key, (pro, rea) in zip(keys, zip(*values.values(), strict=True), strict=True):
            row = table[table["metric"] == key]
            assert row["proactive_mean"].item() == pytest.approx(pro)
            assert row["reactive_mean"].item() == pytest.approx(rea)
    finally:
        r.close()
