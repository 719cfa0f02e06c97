"""Runtime and study exceptions map to HTTP statuses by class (``ERROR_STATUS`` in the app factory), and the
ingest socket answers the runtime's ingest exceptions with their codes (``INGEST_ERROR_CODES``)."""

from __future__ import annotations

import importlib
import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from app.api.app import ERROR_STATUS, create_app
from app.api.routes.live import INGEST_ERROR_CODES
from app.cell.validation import FrameRejected
from app.config import Settings
from app.control.runtime import IngestUnavailable, TrialAlreadyRunning
from app.study.repository import ConflictError, NotFoundError, TrialStateError

#: The documented mapping (docstrings of ERROR_STATUS and of the routes).
DOCUMENTED_STATUS = {
    "app.study.repository.NotFoundError": 404,
    "app.study.repository.ConflictError": 409,
    "app.study.repository.TrialStateError": 409,
    "app.control.runtime.TrialAlreadyRunning": 409,
}
DOCUMENTED_INGEST_CODES = {
    "app.cell.validation.FrameRejected": "rejected",
    "app.control.runtime.IngestUnavailable": "unavailable",
}


def _client_raising(settings: Settings, runtime: Any, exc: Exception) -> TestClient:
    """A client of the real app with one extra route, ``GET /test-raise``, that raises ``exc``."""
    app = create_app(settings, runtime=runtime, scene=False)

    def _raise() -> None:
        raise exc

    app.add_api_route("/test-raise", _raise)
    app.router.routes.insert(0, app.router.routes.pop())  # before the UI's catch-all static mount
    return TestClient(app, raise_server_exceptions=False)


def _dotted(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


@pytest.mark.parametrize("table", ["status", "ingest"])
def test_every_registered_class_exists_where_it_says_and_maps_as_documented(table: str) -> None:
    registered: dict[type[Exception], Any] = ERROR_STATUS if table == "status" else INGEST_ERROR_CODES
    documented = DOCUMENTED_STATUS if table == "status" else DOCUMENTED_INGEST_CODES
    assert {_dotted(cls): value for cls, value in registered.items()} == documented
    for name in documented:
        module, _, attr = name.rpartition(".")
        cls = getattr(importlib.import_module(module), attr)
        assert isinstance(cls, type) and issubclass(cls, Exception), name
        assert cls in registered, name


@pytest.mark.parametrize(
    ("exc", "code"),
    [
        (NotFoundError("participant 7 does not exist"), 404),
        (ConflictError("participant code P01 is taken"), 409),
        (TrialStateError("trial 3 is not running"), 409),
        (TrialAlreadyRunning("trial 2 is running; stop it first"), 409),
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, Exception) else str(v),
)
def test_each_status_path_answers_its_status_with_the_message(
    settings: Settings, runtime: Any, exc: Exception, code: int
) -> None:
    with _client_raising(settings, runtime, exc) as client:
        r = client.get("/test-raise")
    assert r.status_code == code
    assert r.json() == {"detail": str(exc)}


def test_an_unregistered_exception_is_a_500_without_its_message(settings: Settings, runtime: Any) -> None:
    with _client_raising(settings, runtime, KeyError("secret internals")) as client:
        r = client.get("/test-raise")
    assert r.status_code == 500 and "secret" not in r.text


@pytest.mark.parametrize(
    ("exc", "code"),
    [
        (FrameRejected("joint_count", "format 'coco17' needs 17 joints, got 3"), "rejected"),
        (IngestUnavailable("the runtime reads no stream (HRC_HUMAN_SOURCE=sim)"), "unavailable"),
    ],
    ids=["FrameRejected", "IngestUnavailable"],
)
def test_ingest_answers_each_runtime_error_with_its_code(
    make_client: Any, settings: Settings, runtime: Any, exc: Exception, code: str
) -> None:
    def ingest(_message: Any) -> None:
        raise exc

    runtime.ingest = ingest
    client: TestClient = make_client(settings)
    with client.websocket_connect(f"/api/ingest?token={settings.api_token}") as ws:
        assert ws.receive_json()["type"] == "ready"
        ws.send_text(json.dumps({"t": 1.0, "joints": []}))
        err = ws.receive_json()
    assert err["code"] == code and err["detail"] == str(exc)
