"""The trial recorder: live events via the event writer, the result at the end, no duplicates, frames and the
end reason stored, a failing database never raising into the runtime's listener."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from app.api.recorder import TrialRecorder, end_reason
from app.control.metrics import TrialEvent, TrialMetrics


@pytest.fixture
def repo(tmp_path: Path) -> Any:
    from app.study.db import make_engine, upgrade_to_head
    from app.study.repository import StudyRepository

    url = f"sqlite:///{(tmp_path / 'r.db').as_posix()}"
    upgrade_to_head(url)
    engine = make_engine(url)
    yield StudyRepository(engine)
    engine.dispose()


def _trial(repo: Any) -> int:
    from app.study.schemas import ParticipantCreate

    p = repo.create_participant(ParticipantCreate(code="X1"))
    return repo.create_trial(participant_id=p.id, method="reactive").id


def test_events_live_then_result_with_frames_and_reason(repo: Any) -> None:
    from app.study.repository import RecordedFrames

    frames = RecordedFrames(t=np.array([0.0, 0.1, 0.2]), q=np.zeros((3, 6)), skeleton=np.ones((3, 19, 3)))
    metrics = TrialMetrics(method="reactive", duration_s=3.0, completed_tasks=2)
    rec = TrialRecorder(repo, frames_of=lambda m: frames if m is metrics else None)
    rec.start()
    tid = _trial(repo)
    rec.begin(tid)
    live = [TrialEvent(0.0, "trial_started", {}), TrialEvent(1.0, "task_completed", {"index": 0})]
    for ev in live:
        rec.on_event(tid, ev)
    rec.on_event(None, TrialEvent(0.5, "stale_stream", {}))  # outside a trial: ignored
    ended = TrialEvent(3.0, "trial_ended", {"status": "aborted", "reason": "estop"})
    rec.on_trial_end(tid, metrics, [*live, ended], "aborted")
    assert rec.wait_stored(tid, 10.0)
    rec.close()
    t = repo.get_trial(tid)
    assert t.status == "aborted" and t.abort_reason == "estop" and t.metrics.completed_tasks == 2
    assert [e.kind for e in repo.list_events(tid)] == ["trial_started", "task_completed", "trial_ended"]
    stored = repo.load_frames(tid)
    assert stored is not None and len(stored) == 3 and stored.skeleton.shape == (3, 19, 3)
    assert rec.stored == 1 and rec.failed == 0


def test_unknown_status_is_stored_as_aborted_with_it_as_reason(repo: Any) -> None:
    rec = TrialRecorder(repo)
    tid = _trial(repo)
    rec.begin(tid)
    rec.on_trial_end(tid, TrialMetrics(method="reactive"), [], "robot_fault")
    rec.start()
    assert rec.wait_stored(tid, 10.0)
    rec.close()
    t = repo.get_trial(tid)
    assert t.status == "aborted" and t.abort_reason == "robot_fault"


def test_a_failing_database_is_logged_not_raised(repo: Any, caplog: pytest.LogCaptureFixture) -> None:
    rec = TrialRecorder(repo)
    rec.start()
    rec.on_trial_end(999, TrialMetrics(method="reactive"), [], "completed")  # no such trial
    rec.close()
    assert rec.failed == 1 and "storing its result failed" in caplog.text


def test_end_reason() -> None:
    assert (
        end_reason([TrialEvent(1.0, "trial_ended", {"status": "completed", "reason": "duration"})])
        == "duration"
    )
    assert end_reason([TrialEvent(1.0, "task_completed", {})]) is None
