"""Start-up and shutdown: the order (runtime first, then the recorder and the database), the signal hook of
``hrc serve``, the optional 3D view and the operator page mount."""

from __future__ import annotations

import signal
import sys
import threading
import types
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api import app as app_module
from app.api.app import StopOnce, create_app
from app.config import Settings


def test_shutdown_stores_the_running_trial_before_closing_the_database(
    make_client: Any, settings: Settings, runtime: Any, auth: dict[str, str]
) -> None:
    from app.study.db import make_engine
    from app.study.repository import StudyRepository

    c = make_client(settings)
    p = c.post("/api/participants", json={"code": "S1"}, headers=auth).json()
    t = c.post(
        "/api/trials", json={"participant_id": p["id"], "method": "proactive", "duration_s": 60}, headers=auth
    ).json()
    c.__exit__(None, None, None)  # lifespan shutdown: runtime.stop() ends the trial, the recorder stores it
    engine = make_engine(settings.resolved_database_url())
    try:
        stored = StudyRepository(engine).get_trial(t["id"])
        events = StudyRepository(engine).list_events(t["id"])
    finally:
        engine.dispose()
    assert stored.status == "aborted" and stored.metrics is not None
    assert [e.kind for e in events] == ["trial_started", "task_completed", "trial_ended"]


def test_stop_once_runs_once_and_survives_errors() -> None:
    calls = []

    def stop() -> None:
        calls.append(threading.current_thread().name)
        raise RuntimeError("robot already gone")

    once = StopOnce(stop, name="runtime", timeout_s=1.0)
    once()
    once()
    assert len(calls) == 1


def test_signal_stops_the_robot_before_uvicorn_exits(settings: Settings) -> None:
    import uvicorn

    from app.api.server import _uvicorn_server_class

    stopped = threading.Event()
    app = create_app(settings, runtime=object(), scene=False)
    app.state.stop_runtime = stopped.set
    server = _uvicorn_server_class()(uvicorn.Config(app), app)
    server.handle_exit(signal.SIGTERM, None)
    assert stopped.wait(5.0)  # on a helper thread, started by the signal itself
    assert server.should_exit


def test_scene_is_started_with_the_settings_and_stopped(
    monkeypatch: pytest.MonkeyPatch, make_client: Any, settings: Settings, runtime: Any
) -> None:
    made: list[Any] = []

    class FakeScene:
        def __init__(self, rt: Any, cell: Any, *, port: int, host: str, roadmap: Any, token: str) -> None:
            self.args = (rt, cell, port, host, roadmap, token)
            self.started = self.stopped = False
            made.append(self)

        def start(self) -> None:
            self.started = True

        def stop(self) -> None:
            self.stopped = True

        @property
        def port(self) -> int:
            return 18085  # where it really bound

    monkeypatch.setitem(sys.modules, "app.ui.scene", types.SimpleNamespace(CellScene=FakeScene))
    app = create_app(settings.model_copy(update={"viser_port": 18080}), runtime=runtime, scene=True)
    with TestClient(app) as c:
        (scene,) = made
        assert scene.started and scene.args[0] is runtime
        assert scene.args[2:4] == (18080, settings.host)
        assert scene.args[5] == settings.api_token  # viewers need the operator token
        info = c.get("/api/info", headers={"Authorization": f"Bearer {settings.api_token}"}).json()
        assert info["viser_port"] == 18085  # clients are told the bound port
    assert scene.stopped


def test_a_failing_scene_does_not_stop_the_server(
    monkeypatch: pytest.MonkeyPatch, settings: Settings, runtime: Any
) -> None:
    class Broken:
        def __init__(self, *a: Any, **k: Any) -> None:
            raise OSError("port in use")

    monkeypatch.setitem(sys.modules, "app.ui.scene", types.SimpleNamespace(CellScene=Broken))
    with TestClient(create_app(settings, runtime=runtime, scene=True)) as c:
        assert c.get("/api/health").json()["status"] == "ok"


def test_operator_page_is_served_at_root(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any, settings: Settings, runtime: Any
) -> None:
    (tmp_path / "index.html").write_text("<!doctype html><title>hrc operator</title>")
    monkeypatch.setattr(app_module, "UI_STATIC_DIR", tmp_path)
    with TestClient(create_app(settings, runtime=runtime, scene=False)) as c:
        page = c.get("/")
        assert page.status_code == 200 and "hrc operator" in page.text
        assert c.get("/api/health").status_code == 200  # the API routes come before the mount
        assert c.get("/docs").status_code == 200


def test_without_operator_page_root_redirects_to_docs(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Any, settings: Settings, runtime: Any
) -> None:
    monkeypatch.setattr(app_module, "UI_STATIC_DIR", tmp_path / "missing")
    with TestClient(create_app(settings, runtime=runtime, scene=False)) as c:
        r = c.get("/", follow_redirects=False)
        assert r.status_code in (302, 307) and r.headers["location"] == "/docs"


def test_trial_settings_never_hold_secrets(settings: Settings) -> None:
    from app.api.routes.trials import _settings_snapshot

    snap = _settings_snapshot(
        settings.model_copy(update={"database_url": "postgresql+psycopg://lab:s3cret@db/hrc"})
    )
    assert "api_token" not in snap
    assert "s3cret" not in snap["database_url"] and "lab:***@db" in snap["database_url"]


def test_a_runtime_that_cannot_start_fails_the_start_cleanly(settings: Settings, runtime: Any) -> None:
    def broken_start() -> None:
        raise RuntimeError("robot not reachable at 192.168.1.10")

    runtime.start = broken_start
    app = create_app(settings, runtime=runtime, scene=False)
    with pytest.raises(RuntimeError, match="not reachable"), TestClient(app):
        pass
    assert app.state.hrc is None and runtime.stopped == 1  # stop() still ran (robot.stop in its finally)
