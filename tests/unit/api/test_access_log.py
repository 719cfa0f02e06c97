"""The operator token never appears in plain text in the logs: uvicorn's access log of a request and its
log of a WebSocket handshake with ``?token=`` show ``token=***``."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from starlette.applications import Starlette
from starlette.responses import PlainTextResponse
from starlette.routing import Route, WebSocketRoute
from starlette.websockets import WebSocket

from app.api import server as server_mod
from app.api.server import REDACTED_LOGGERS, RedactSecrets, install_log_redaction, redact_secrets
from app.config import Settings

SECRET = "s3cret-operator-token-0123456789"


def test_redact_secrets_hides_only_the_token_values() -> None:
    assert (
        redact_secrets(f"GET /api/live?token={SECRET}&x=1 HTTP/1.1") == "GET /api/live?token=***&x=1 HTTP/1.1"
    )
    assert redact_secrets(f"/a?b=2&TOKEN={SECRET}") == "/a?b=2&TOKEN=***"
    assert redact_secrets("/api/trials?limit=5") == "/api/trials?limit=5"


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


async def _hello(request: Any) -> PlainTextResponse:
    return PlainTextResponse("hi")


async def _socket(websocket: WebSocket) -> None:
    await websocket.accept()
    await websocket.close()


@pytest.fixture
def uvicorn_server() -> Iterator[tuple[str, _Records]]:
    """A real uvicorn server (its own logging configuration) on a free port, with the redaction installed
    as ``run_server`` installs it, and a handler that records what its loggers write."""
    import uvicorn

    app = Starlette(routes=[Route("/hello", _hello), WebSocketRoute("/ws", _socket)])
    config = uvicorn.Config(app, host="127.0.0.1", port=0, log_level="info", lifespan="off")
    install_log_redaction()
    records = _Records()
    for name in REDACTED_LOGGERS:
        logging.getLogger(name).addHandler(records)
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10.0
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.01)
    assert server.started, "uvicorn did not start"
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"127.0.0.1:{port}", records
    finally:
        server.should_exit = True
        thread.join(10.0)
        for name in REDACTED_LOGGERS:
            logging.getLogger(name).removeHandler(records)


def test_the_token_in_a_query_is_not_in_the_access_log(uvicorn_server: tuple[str, _Records]) -> None:
    from websockets.sync.client import connect

    address, records = uvicorn_server
    assert httpx.get(f"http://{address}/hello?token={SECRET}&x=1", timeout=5.0).status_code == 200
    with connect(f"ws://{address}/ws?token={SECRET}", open_timeout=5.0):
        pass
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and not (
        any("/hello" in line for line in records.lines) and any("/ws" in line for line in records.lines)
    ):
        time.sleep(0.01)
    logged = "\n".join(records.lines)
    assert "/hello?token=***&x=1" in logged and "/ws?token=***" in logged, logged
    assert SECRET not in logged


def test_run_server_installs_the_redaction(monkeypatch: pytest.MonkeyPatch, tmp_path: Any) -> None:
    for name in REDACTED_LOGGERS:
        logger = logging.getLogger(name)
        for f in [f for f in logger.filters if isinstance(f, RedactSecrets)]:
            logger.removeFilter(f)

    class _NoServer:
        def __init__(self, config: Any, app: Any) -> None:
            pass

        def run(self) -> None:
            pass

    monkeypatch.setattr(server_mod, "_uvicorn_server_class", lambda: _NoServer)
    settings = Settings(_env_file=None, data_dir=tmp_path, api_token=SECRET)
    server_mod.run_server(settings, log_level="warning")
    for name in REDACTED_LOGGERS:
        assert any(isinstance(f, RedactSecrets) for f in logging.getLogger(name).filters), name
