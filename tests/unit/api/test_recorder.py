"""The trial recorder: live events via the event writer, the result at the end, no duplicates, frames and the
end reason stored, a failing database never raising into the runtime's listener."""

from __future__ import annotations

import time
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
    assert stored is not None and len(stored) == 3 and stored.skeleton.shape == (3, 1, 19, 3)
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


def test_a_running_trial_is_checkpointed_then_ends_with_its_whole_recording(repo: Any) -> None:
    """Checkpoints append the frames recorded since the last one and replace the metrics; the API shows
    neither while the trial runs; the end stores the whole recording once; an interrupted trial keeps the
    last checkpoint and ends when it was taken."""
    import threading

    from app.api.recorder import Checkpoint
    from app.study.repository import RecordedFrames

    n_frames = [0]
    asked: list[int] = []
    took = threading.Event()

    def recording(first: int, n: int) -> RecordedFrames:
        t = np.arange(first, n) / 30
        return RecordedFrames(t=t, q=np.full((t.size, 6), 0.5), skeleton=np.ones((t.size, 19, 3)))

    def checkpoint_of(trial_id: int, first_frame: int) -> Checkpoint | None:
        asked.append(first_frame)
        n_frames[0] += 7  # the runtime recorded 7 frames since
        took.set()
        m = TrialMetrics(method="reactive", duration_s=n_frames[0] / 30, completed_tasks=len(asked))
        return Checkpoint(m, recording(first_frame, n_frames[0]), first_frame)

    rec = TrialRecorder(repo, checkpoint_of=checkpoint_of, checkpoint_period_s=0.01)
    tid = _trial(repo)
    rec.begin(tid)
    rec.on_event(tid, TrialEvent(0.0, "trial_started", {}))
    rec.start()
    for _ in range(3):
        took.clear()
        assert took.wait(10.0)
    deadline = time.monotonic() + 10.0
    while rec.checkpoints < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    rec_frames = repo.load_frames(tid)
    running = repo.get_trial(tid)
    assert running.status == "running" and running.metrics is None and running.ended_at is None
    assert rec_frames is not None and np.all(np.diff(rec_frames.t) > 0)  # appended, no duplicates
    assert asked[:3] == [0, 7, 14]
    assert [e.kind for e in repo.list_events(tid)] == ["trial_started"]  # flushed with the checkpoint

    metrics = TrialMetrics(method="reactive", duration_s=2.0, completed_tasks=9)
    whole = recording(0, 60)
    rec._frames_of = lambda m: whole if m is metrics else None
    rec.on_trial_end(tid, metrics, [], "completed")
    assert rec.wait_stored(tid, 10.0)
    rec.close()
    done = repo.get_trial(tid)
    assert done.status == "completed" and done.metrics.completed_tasks == 9
    stored = repo.load_frames(tid)
    assert stored is not None and len(stored) == 60 and np.array_equal(stored.t, whole.t)


def test_an_interrupted_trial_ends_at_its_last_checkpoint(repo: Any) -> None:
    from datetime import UTC, datetime, timedelta

    from app.study.repository import RecordedFrames

    tid = _trial(repo)
    at = datetime.now(UTC) - timedelta(minutes=5)
    t = np.arange(10) / 30
    for k in range(2):
        m = TrialMetrics(method="reactive", duration_s=(k + 1) * 0.3, completed_tasks=k)
        frames = RecordedFrames(t=t[5 * k : 5 * k + 5], q=np.zeros((5, 6)), skeleton=None)
        repo.checkpoint_trial(tid, metrics=m, frames=frames, at=at + timedelta(seconds=k))
    never = _trial_of_other(repo)
    assert repo.abort_interrupted_trials() == [tid, never]
    got = repo.get_trial(tid)
    assert got.status == "aborted" and "interrupted" in (got.abort_reason or "")
    assert got.ended_at == at + timedelta(seconds=1) and got.metrics.completed_tasks == 1
    assert np.array_equal(repo.load_frames(tid).t, t)
    other = repo.get_trial(never)
    assert other.metrics is None and other.ended_at is not None and other.ended_at > at + timedelta(minutes=4)


def _trial_of_other(repo: Any) -> int:
    from app.study.schemas import ParticipantCreate

    p = repo.create_participant(ParticipantCreate(code="X2"))
    return repo.create_trial(participant_id=p.id, method="proactive").id
