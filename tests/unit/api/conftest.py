"""Fixtures of the API tests: a real SQLite study database in a temporary directory, and a small runtime
double with the ``Runtime`` contract (no threads of its own: tests drive it)."""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Callable, Iterator
from contextlib import ExitStack, suppress
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.app import create_app
from app.api.live_hub import LiveLimits
from app.cell.validation import FrameRejected
from app.config import Settings
from app.control.metrics import TrialEvent, TrialMetrics
from app.control.runtime import TrialAlreadyRunning

TOKEN = "test-token-0123456789abcdef"


@dataclass(frozen=True)
class FakeSnapshot:
    t: float = 0.0
    trial_id: int | None = None
    state: str = "idle"
    method: str | None = None
    speed_scale: float = 1.0
    separation_m: float = float("inf")
    required_separation_m: float = 0.3
    planning_ms: tuple[float, ...] = ()
    counters: dict[str, int] = field(default_factory=dict)
    q: tuple[float, ...] = (0.0, -1.57, 1.57, -1.57, -1.57, 0.0)
    p_world_tcp: tuple[float, ...] = (0.4, 0.0, 0.3)
    stale: bool = False
    estopped: bool = False
    trial_elapsed_s: float | None = None
    trial_duration_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "t": self.t,
            "trial_id": self.trial_id,
            "state": self.state,
            "method": self.method,
            "speed_scale": self.speed_scale,
            "separation_m": self.separation_m,
            "required_separation_m": self.required_separation_m,
            "planning_ms": list(self.planning_ms),
            "counters": dict(self.counters),
            "q": list(self.q),
            "p_world_tcp": list(self.p_world_tcp),
            "stale": self.stale,
            "estopped": self.estopped,
            "trial_elapsed_s": self.trial_elapsed_s,
            "trial_duration_s": self.trial_duration_s,
        }


class FakeSubscription:
    def __init__(self, maxsize: int) -> None:
        self._q: queue.Queue[FakeSnapshot] = queue.Queue(maxsize=maxsize)
        self.closed = False

    def put(self, snap: FakeSnapshot) -> None:
        while True:
            try:
                self._q.put_nowait(snap)
                return
            except queue.Full:
                with suppress(queue.Empty):
                    self._q.get_nowait()

    def get(self, timeout: float | None = None) -> FakeSnapshot | None:
        try:
            return self._q.get(timeout=timeout) if timeout else self._q.get_nowait()
        except queue.Empty:
            return None

    def close(self) -> None:
        self.closed = True


class FakeRuntime:
    """The ``Runtime`` contract, driven by the test: ``finish_trial`` ends the running trial."""

    def __init__(self) -> None:
        self.started = 0
        self.stopped = 0
        self.running_trial_id: int | None = None
        self.trial_args: dict[str, Any] = {}
        self.estopped = False
        self.ingested: list[Any] = []
        self.rejected: dict[str, int] = {}
        self.servo_overruns = 0
        self.subscriptions: list[FakeSubscription] = []
        self.trial_listeners: list[Callable[..., None]] = []
        self.event_listeners: list[Callable[..., None]] = []
        self._snap = FakeSnapshot()
        self._lock = threading.Lock()
        self.stop_reasons: list[str] = []

    def start(self) -> None:
        self.started += 1

    def stop(self) -> None:
        self.stopped += 1
        if self.running_trial_id is not None:
            self.finish_trial("aborted")

    def add_trial_listener(self, fn: Callable[..., None]) -> None:
        self.trial_listeners.append(fn)

    def add_event_listener(self, fn: Callable[..., None]) -> None:
        self.event_listeners.append(fn)

    def start_trial(self, *, trial_id: int, method: str, duration_s: float, seed: int) -> None:
        with self._lock:
            if self.running_trial_id is not None:
                raise TrialAlreadyRunning(f"trial {self.running_trial_id} is running")
            if self.estopped:
                raise RuntimeError("E-stopped: reset first")
            self.running_trial_id = trial_id
            self.trial_args = {"method": method, "duration_s": duration_s, "seed": seed}
        self.emit(TrialEvent(0.0, "trial_started", {"method": method, "seed": seed}))
        self.publish(replace(self._snap, trial_id=trial_id, method=method, trial_duration_s=duration_s))

    def emit(self, event: TrialEvent) -> None:
        for fn in self.event_listeners:
            fn(self.running_trial_id, event)

    def finish_trial(self, status: str = "completed", *, extra_events: int = 1) -> None:
        trial_id = self.running_trial_id
        assert trial_id is not None
        method = self.trial_args["method"]
        events = [TrialEvent(0.0, "trial_started", {"method": method, "seed": self.trial_args["seed"]})]
        for k in range(extra_events):
            events.append(TrialEvent(0.5 + k, "task_completed", {"station": "drop_1", "index": k}))
        events.append(TrialEvent(2.0, "trial_ended", {"status": status, "reason": "test"}))
        metrics = TrialMetrics(method=method, duration_s=2.0, completed_tasks=extra_events, plans_computed=3)
        self.running_trial_id = None
        for fn in self.trial_listeners:
            fn(trial_id, metrics, events, status)

    def stop_trial(self, reason: str = "operator") -> None:
        self.stop_reasons.append(reason)
        if self.running_trial_id is not None:
            self.finish_trial("stopped")

    def estop(self, source: str = "api") -> None:
        self.estopped = True
        if self.running_trial_id is not None:
            self.finish_trial("estop")
        self.publish(replace(self._snap, estopped=True, state="stopped", speed_scale=0.0))

    def reset(self) -> None:
        if not self.estopped:
            raise RuntimeError("nothing to reset: the robot is not stopped")
        self.estopped = False
        self.publish(replace(self._snap, estopped=False, state="idle"))

    def snapshot(self) -> FakeSnapshot:
        return self._snap

    def publish(self, snap: FakeSnapshot) -> None:
        self._snap = snap
        for s in list(self.subscriptions):
            s.put(snap)

    def subscribe(self, maxsize: int = 8) -> FakeSubscription:
        sub = FakeSubscription(maxsize)
        self.subscriptions.append(sub)
        return sub

    def ingest(self, message: Any) -> None:
        """Like the stream source: the text as received, parsed here; rejections counted by reason."""
        try:
            obj = json.loads(message) if isinstance(message, str | bytes) else message
        except ValueError:
            obj = None
        if not isinstance(obj, dict) or "joints" not in obj:
            self.rejected["malformed"] = self.rejected.get("malformed", 0) + 1
            raise FrameRejected("malformed", "a frame needs 'joints'")
        self.ingested.append(obj)

    def frame_counts(self) -> dict[str, Any]:
        return {
            "frames_received": len(self.ingested) + sum(self.rejected.values()),
            "frames_rejected": {"total": sum(self.rejected.values()), "by_reason": dict(self.rejected)},
            "servo_overruns": self.servo_overruns,
        }


class FakeClock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(
        _env_file=None,
        data_dir=tmp_path / "var",
        api_token=TOKEN,
        database_url=f"sqlite:///{(tmp_path / 'study.db').as_posix()}",
    )


@pytest.fixture
def runtime() -> FakeRuntime:
    return FakeRuntime()


@pytest.fixture
def fake_clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def make_client(runtime: FakeRuntime, fake_clock: FakeClock) -> Iterator[Callable[..., TestClient]]:
    """``make_client(settings, **limits)``: a ``TestClient`` entered as a context manager (the lifespan runs),
    left at the end of the test (the lifespan's shutdown runs)."""
    with ExitStack() as stack:

        def _make(settings: Settings, **limits: Any) -> TestClient:
            app = create_app(
                settings, runtime=runtime, limits=LiveLimits(clock=fake_clock, **limits), scene=False
            )
            return stack.enter_context(TestClient(app))

        yield _make


@pytest.fixture
def client(make_client: Callable[..., TestClient], settings: Settings) -> TestClient:
    return make_client(settings)


@pytest.fixture
def auth() -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKEN}"}
