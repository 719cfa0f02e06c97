"""The shared viser lifecycle: start runs build then the worker; a failing build leaves nothing running."""

from __future__ import annotations

import threading

import pytest

from app.ui.viser_server import CAMERA_LOOK_AT, ViserServerThread


def test_start_builds_runs_the_worker_and_stop_ends_both() -> None:
    srv = ViserServerThread(host="127.0.0.1", port=0, name="test-viser")
    built: list[object] = []
    ticks = threading.Event()

    def worker(stop: threading.Event) -> None:
        while not stop.wait(0.01):
            ticks.set()

    server = srv.start(built.append, worker)
    try:
        assert built == [server] and srv.server is server
        assert tuple(server.initial_camera.look_at) == pytest.approx(CAMERA_LOOK_AT)
        assert srv.port > 0 and ticks.wait(5.0) and srv.running
        with pytest.raises(RuntimeError, match="called twice"):
            srv.start(built.append, worker)
    finally:
        srv.stop()
    assert not srv.running and srv.server is None
    srv.stop()  # idempotent


def test_a_failing_build_stops_the_server_and_starts_no_thread() -> None:
    srv = ViserServerThread(host="127.0.0.1", port=0, name="test-viser")

    def build(_server: object) -> None:
        raise ValueError("the scene could not be drawn")

    with pytest.raises(ValueError, match="could not be drawn"):
        srv.start(build, lambda stop: None)
    assert srv.server is None and not srv.running
