"""EventWriter: batched (due by a fake clock), bounded, thread-safe, flushed on close, retried on errors."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest
from sqlalchemy.exc import OperationalError

from app.control.metrics import TrialEvent
from app.study.db import make_engine, upgrade_to_head
from app.study.repository import EventWriter, StudyRepository, TrialStateError
from app.study.schemas import ParticipantCreate


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class FlakyRepo:
    """Records batches; fails while ``failing`` is set."""

    def __init__(self) -> None:
        self.batches: list[list[TrialEvent]] = []
        self.failing = False

    def add_events(self, trial_id: int, events: Iterable[TrialEvent]) -> int:
        if self.failing:
            raise OperationalError("INSERT", {}, Exception("database is locked"))
        batch = list(events)
        self.batches.append(batch)
        return len(batch)


def _ev(i: int) -> TrialEvent:
    return TrialEvent(t=float(i), kind="violation", payload={"i": i})


@pytest.fixture
def repo_and_trial(tmp_path: Path) -> Iterator[tuple[StudyRepository, int]]:
    url = f"sqlite:///{tmp_path / 'ev.db'}"
    upgrade_to_head(url)
    repo = StudyRepository(make_engine(url))
    p = repo.create_participant(ParticipantCreate(code="E"))
    yield repo, repo.create_trial(participant_id=p.id, method="proactive").id
    repo.close()


def test_batches_are_written_when_due_and_on_close() -> None:
    clock, repo = FakeClock(), FlakyRepo()
    w = EventWriter(repo, 1, flush_interval_s=1.0, clock=clock)  # type: ignore[arg-type]
    for i in range(5):
        clock.t = i * 0.2  # 0.0 .. 0.8 s: not due yet
        w.write(_ev(i))
    assert repo.batches == [] and w.pending == 5
    clock.t = 1.0
    w.write(_ev(5))  # due: the whole buffer in one batch
    assert [len(b) for b in repo.batches] == [6] and w.written == 6
    clock.t = 1.5
    w.write(_ev(6))
    assert w.pending == 1
    w.close()
    assert [e.payload["i"] for b in repo.batches for e in b] == list(range(7))
    with pytest.raises(TrialStateError, match="closed"):
        w.write(_ev(7))
    w.close()  # idempotent


def test_full_buffer_flushes_and_overflow_drops_oldest_while_the_database_fails() -> None:
    clock, repo = FakeClock(), FlakyRepo()
    w = EventWriter(repo, 1, max_buffer=4, clock=clock)  # type: ignore[arg-type]
    for i in range(4):
        w.write(_ev(i))
    assert [len(b) for b in repo.batches] == [4]  # full -> flushed at once
    repo.failing = True
    for i in range(4, 10):
        w.write(_ev(i))
    assert w.pending == 4 and w.dropped == 2 and w.failed_flushes >= 1  # bounded; oldest dropped
    repo.failing = False
    assert w.flush() == 4
    assert [e.payload["i"] for e in repo.batches[-1]] == [6, 7, 8, 9]
    assert w.written == 8


def test_flush_interval_must_be_at_most_one_second() -> None:
    with pytest.raises(ValueError, match="flush_interval_s"):
        EventWriter(FlakyRepo(), 1, flush_interval_s=2.0)  # type: ignore[arg-type]


def test_background_flusher_and_concurrent_writers(repo_and_trial: tuple[StudyRepository, int]) -> None:
    repo, trial_id = repo_and_trial
    n_threads, per_thread = 4, 150
    # A small buffer: bursts fill it, and the writers then flush it themselves (nothing is dropped).
    with repo.event_writer(trial_id, flush_interval_s=0.05, max_buffer=64) as w:

        def produce(k: int) -> None:
            for i in range(per_thread):  # all at t = 0: list_events then returns insertion order
                w.write(TrialEvent(t=0.0, kind="violation", payload={"i": k * 1000 + i}))

        threads = [threading.Thread(target=produce, args=(k,)) for k in range(n_threads)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=30)
        # The flusher writes without close(): wait (bounded) until everything is in.
        deadline = time.monotonic() + 30
        while repo.count_events(trial_id) < n_threads * per_thread and time.monotonic() < deadline:
            time.sleep(0.02)
        assert repo.count_events(trial_id) == n_threads * per_thread
    assert w.dropped == 0 and w.written == n_threads * per_thread
    ids = [e.payload["i"] for e in repo.list_events(trial_id, limit=10_000)]
    assert sorted(ids) == sorted(k * 1000 + i for k in range(n_threads) for i in range(per_thread))
    for k in range(n_threads):  # each producer's events stay in its order
        mine = [i for i in ids if i // 1000 == k]
        assert mine == sorted(mine)
