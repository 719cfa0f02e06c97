"""Data integrity with a real kill: a process that is writing a trial's events is SIGKILLed; the database
still opens, the trial is marked aborted at the next start, and every event up to the last flush is kept."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

from sqlalchemy import text

from app.study.db import make_engine
from app.study.repository import open_repository

REPO_ROOT = Path(__file__).resolve().parents[2]
READ_TIMEOUT_S = 60.0

# The child: start a trial and write events continuously through an EventWriter (default: flushed at least
# once a second); it reports every flush on stdout and would stop by itself after 120 s.
CHILD = """
import sys, time
from app.control.metrics import TrialEvent
from app.study.repository import open_repository
from app.study.schemas import ParticipantCreate

repo = open_repository(sys.argv[1])
p = repo.create_participant(ParticipantCreate(code="killed-01"))
trial = repo.create_trial(participant_id=p.id, method="proactive", seed=1)
print(f"trial {trial.id}", flush=True)
writer = repo.event_writer(trial.id, on_flush=lambda n: print(f"flushed {n}", flush=True))
i = 0
deadline = time.monotonic() + 120.0
while time.monotonic() < deadline:
    writer.write(TrialEvent(t=i * 0.01, kind="violation", payload={"i": i}))
    i += 1
    time.sleep(0.001)
"""


def _read_line(proc: subprocess.Popen[str], deadline: float) -> str:
    assert proc.stdout is not None
    while True:
        remaining = deadline - time.monotonic()
        assert remaining > 0, "the child did not report in time"
        ready, _, _ = select.select([proc.stdout], [], [], remaining)
        if ready:
            line = proc.stdout.readline()
            assert line, (
                f"the child exited early (rc {proc.poll()}): {proc.stderr.read() if proc.stderr else ''}"
            )
            return line.strip()


def test_sigkill_during_trial_keeps_flushed_events_and_aborts_the_trial(db_url: str) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, db_url],
        cwd=REPO_ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + READ_TIMEOUT_S
        first = _read_line(proc, deadline)
        assert first.startswith("trial "), first
        trial_id = int(first.split()[1])
        flushed = []
        while len(flushed) < 2:  # at least two batches are in; more events are waiting in the buffer
            line = _read_line(proc, deadline)
            if line.startswith("flushed "):
                flushed.append(int(line.split()[1]))
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()

    # The database opens and is consistent; the trial is still 'running' until the next start.
    engine = make_engine(db_url)
    try:
        if engine.dialect.name == "sqlite":
            with engine.connect() as conn:
                assert conn.execute(text("PRAGMA integrity_check")).scalar() == "ok"
    finally:
        engine.dispose()
    repo = open_repository(db_url)  # a tool beside the app: does not touch running trials
    assert repo.get_trial(trial_id).status == "running"
    repo.close()

    # Next start of the app: interrupted trials become aborted; the flushed events are all there, in order.
    repo = open_repository(db_url, abort_interrupted=True)
    try:
        trial = repo.get_trial(trial_id)
        assert trial.status == "aborted" and trial.ended_at is not None
        assert trial.abort_reason is not None and "interrupted" in trial.abort_reason
        events = repo.list_events(trial_id, limit=10**7)
        assert len(events) >= flushed[-1] > flushed[0] > 0
        assert [e.payload["i"] for e in events] == list(range(len(events)))  # a gap-free prefix
    finally:
        repo.close()
