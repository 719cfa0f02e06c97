"""The live plan jobs let each frame's decision go first: a job that reads its clock while the frame thread
is between reading the source and its decision waits there (:class:`ForegroundGate`), and the trial engine
holds that foreground for exactly that stretch."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from app.cell.clock import WallClock
from app.config import Settings
from app.control.backup import BackupComputer, BackupRequest, ForegroundGate, InlinePlanJobs, PoolPlanJobs
from app.control.headless import run_headless_trial
from app.control.people import People
from app.control.stack import PlanningStack
from app.control.supervisor import Supervisor
from app.prediction.forecast import HumanForecast
from app.prediction.skeleton import NUM_JOINTS, HumanFrame

# (long enough that a wait which should not have ended could not have ended by chance)
LONG_S = 30.0


def _clock_reader(gate: ForegroundGate) -> tuple[threading.Thread, threading.Event]:
    """A thread that reads ``gate``'s clock once, and an event set when it has."""
    done = threading.Event()

    def read() -> None:
        gate.now()
        done.set()

    th = threading.Thread(target=read, daemon=True)
    th.start()
    return th, done


def test_a_job_reading_the_clock_waits_until_the_foreground_ends() -> None:
    gate = ForegroundGate(max_wait_s=LONG_S)
    with gate.foreground():
        th, done = _clock_reader(gate)
        assert not done.wait(0.3)  # held while the frame is in the foreground
    assert done.wait(LONG_S)  # and goes on once it is out of it
    th.join(LONG_S)
    assert gate.waits == 1 and gate.waited_s > 0.0


def test_without_a_foreground_a_job_reads_the_clock_at_once() -> None:
    gate = ForegroundGate(max_wait_s=LONG_S)
    th, done = _clock_reader(gate)
    assert done.wait(LONG_S)
    th.join(LONG_S)
    with gate.foreground():
        pass
    th, done = _clock_reader(gate)  # a foreground that has ended holds nothing
    assert done.wait(LONG_S)
    assert gate.waits == 0


def test_the_thread_in_the_foreground_never_waits_for_itself() -> None:
    gate = ForegroundGate(max_wait_s=0.05)
    with gate.foreground():
        t0 = gate.now()
        assert gate.now() >= t0
    assert gate.waits == 0


def test_a_foreground_that_does_not_end_holds_a_job_no_longer_than_max_wait() -> None:
    gate = ForegroundGate(max_wait_s=0.05)
    with gate.foreground():
        th, done = _clock_reader(gate)
        assert done.wait(LONG_S)  # (the frame thread stalls: the job goes on after max_wait_s)
        th.join(LONG_S)
    assert gate.waits == 1 and gate.waited_s >= 0.05


def test_max_wait_must_be_positive() -> None:
    with pytest.raises(ValueError, match="max_wait_s"):
        ForegroundGate(max_wait_s=0.0)


@dataclass
class _Result:
    ok: bool = False
    plan: Any = None
    reason: str = "blocked"


class _ClockedPlanner:
    """A planner that reads its clock once per query and finds no plan."""

    def __init__(self, timer: Any = time.perf_counter) -> None:
        self.timer = timer

    def with_timer(self, timer: Any) -> _ClockedPlanner:
        return _ClockedPlanner(timer)

    def plan(self, **_: Any) -> _Result:
        self.timer()
        return _Result()


def _request(key: int) -> BackupRequest:
    frame = HumanFrame(0.0, np.zeros((NUM_JOINTS, 3)))
    return BackupRequest(
        key=key,
        t_request=0.0,
        t_start=0.1,
        q_start=np.zeros(6),
        qd_start=np.zeros(6),
        goal="A",
        forecast=HumanForecast.hold(frame),
        deadline_s=LONG_S,
    )


def test_the_pool_plans_on_the_gate_clock_and_a_frame_in_the_foreground_goes_first() -> None:
    planner = _ClockedPlanner()
    computer = BackupComputer(planner, lambda plan, qd0: None, None, deadline_s=LONG_S, workers=1)  # type: ignore[arg-type]
    jobs = PoolPlanJobs(computer, max_jobs=1, clock=WallClock(), gate=ForegroundGate(max_wait_s=LONG_S))
    try:
        assert jobs.compute.planner.timer == jobs.gate.now and jobs.compute.timer == jobs.gate.now
        assert computer.planner is planner  # the caller's computer is left as it was
        with jobs.foreground():
            jobs.submit(_request(1))
            time.sleep(0.3)
            assert jobs.peek(1) is None  # the job waits for the frame's decision
        deadline = time.monotonic() + LONG_S
        while (out := jobs.peek(1)) is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert out is not None and out.status == "failed"
        assert jobs.gate.waits >= 1
    finally:
        jobs.close()


def test_the_engine_holds_the_foreground_from_reading_the_source_to_the_decision(
    stack: PlanningStack, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The frame's decision is made in the foreground; the other people's catching up, after it, is not."""
    inside = {"now": False}
    seen: list[tuple[str, bool]] = []

    @contextlib.contextmanager
    def foreground(self: InlinePlanJobs) -> Iterator[None]:
        assert not inside["now"], "the foreground is not reentrant"
        inside["now"] = True
        try:
            yield
        finally:
            inside["now"] = False

    on_frame, catch_up = Supervisor.on_frame, People.catch_up

    def decide(self: Supervisor, *args: Any, **kwargs: Any) -> Any:
        seen.append(("decision", inside["now"]))
        return on_frame(self, *args, **kwargs)

    def caught_up(self: People) -> None:
        seen.append(("catch_up", inside["now"]))
        catch_up(self)

    monkeypatch.setattr(InlinePlanJobs, "foreground", foreground)
    monkeypatch.setattr(Supervisor, "on_frame", decide)
    monkeypatch.setattr(People, "catch_up", caught_up)
    settings = Settings(human_source="sim", robot="sim", planner_workers=1)
    run_headless_trial(
        settings=settings, method="proactive", duration_s=1.0, seed=7, stack=stack, fixed_compute_s=0.01
    )
    decisions = [fg for kind, fg in seen if kind == "decision"]
    after = [fg for kind, fg in seen if kind == "catch_up"]
    assert len(decisions) >= 20 and all(decisions)
    assert len(after) == len(decisions) and not any(after)
