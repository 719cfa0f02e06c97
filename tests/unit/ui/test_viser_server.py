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


# ---- access: the operator token, and a port another program holds ------------------------------------

TOKEN = "view-token-0123456789abcdef"


def _viewer(port: int, query: str = "", **kw: object) -> object:
    """A viewer's WebSocket as viser's browser client opens it (its version as the subprotocol)."""
    import viser
    from websockets.sync.client import connect

    return connect(
        f"ws://127.0.0.1:{port}/{query}",
        subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
        open_timeout=10,
        close_timeout=5,
        **kw,
    )


def _first_message_or_close(ws: object) -> tuple[bytes | None, int | None]:
    from websockets.exceptions import ConnectionClosed

    try:
        return ws.recv(timeout=10), None  # type: ignore[attr-defined]
    except ConnectionClosed as exc:
        return None, exc.rcvd.code if exc.rcvd is not None else None


def test_a_viewer_needs_the_operator_token() -> None:
    srv = ViserServerThread(host="127.0.0.1", port=0, name="test-viser", token=TOKEN)
    server = srv.start(lambda s: s.scene.add_frame("/cell", show_axes=False), lambda stop: None)
    try:
        for query, headers in (
            ("", None),
            ("?token=wrong", None),
            ("", {"Authorization": "Bearer wrong"}),
        ):
            with _viewer(srv.port, query, additional_headers=headers) as ws:
                msg, code = _first_message_or_close(ws)
            assert msg is None and code == 1008, (query, headers)  # closed before any of the scene
        for query, headers in (
            (f"?token={TOKEN}", None),
            ("", {"Authorization": f"Bearer {TOKEN}"}),
            ("", {"Cookie": f"theme=dark; hrc_token={TOKEN}"}),
        ):
            with _viewer(srv.port, query, additional_headers=headers) as ws:
                msg, code = _first_message_or_close(ws)
            assert msg is not None and code is None, (query, headers)
        assert server.get_port() == srv.port
    finally:
        srv.stop()


def test_a_taken_port_is_an_error_not_a_move_to_the_next() -> None:
    import socket

    from app.ui.viser_server import PortInUse, check_port_free

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        with pytest.raises(PortInUse, match=f"port {port} on 127.0.0.1 is in use"):
            check_port_free("127.0.0.1", port)
        srv = ViserServerThread(host="127.0.0.1", port=port, name="test-viser")
        with pytest.raises(PortInUse):
            srv.start(lambda s: None, lambda stop: None)
        assert srv.server is None and not srv.running
    check_port_free("127.0.0.1", 0)  # any free port: never taken
