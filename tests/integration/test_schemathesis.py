"""Property-based fuzzing of the OpenAPI schema (schemathesis): no request, valid or not, gets a 5xx, and
every response has a documented status code, the documented content type and a body of the documented
schema.

The app is the real one (real runtime on the simulated cell, real SQLite database); schemathesis starts its
lifespan when it loads the schema over ASGI and the fixture shuts it down. Every operation is fuzzed with
schema-conforming data (positive) and, where it takes input, with schema-violating data (negative), with the
operator token. Bounded: a few examples per operation, no example database.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error
from schemathesis.python.asgi import shutdown_lifespans
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from app.api.app import create_app
from app.config import Settings

TOKEN = "fuzz-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MAX_EXAMPLES = 6
#: Every response: no 5xx, a documented status code, the documented content type, and a body that fits the
#: documented schema.
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]


def _operations() -> list[tuple[str, str, GenerationMode]]:
    """(method, path, mode) of every operation, from the schema of an app that is built but not started."""
    paths = create_app(Settings(_env_file=None), scene=False).openapi()["paths"]
    ops = []
    for path, methods in paths.items():
        for method, spec in methods.items():
            ops.append((method.upper(), path, GenerationMode.POSITIVE))
            if spec.get("parameters") or spec.get("requestBody"):
                ops.append((method.upper(), path, GenerationMode.NEGATIVE))
    return ops


def _seed(repo: Any) -> None:
    """A few records, so that generated small ids hit real rows (trials with metrics and events too)."""
    from app.control.metrics import TrialEvent, TrialMetrics
    from app.study.schemas import ParticipantCreate, StudySessionCreate

    session = repo.create_session(StudySessionCreate(name="fuzz"))
    for k, code in enumerate(("F1", "F2", "F3")):
        p = repo.create_participant(ParticipantCreate(code=code, age=30 + k))
        for method in ("proactive", "reactive"):
            t = repo.create_trial(participant_id=p.id, method=method, session_id=session.id, seed=k)
            events = [
                TrialEvent(0.0, "trial_started", {"method": method}),
                TrialEvent(1.0, "trial_ended", {}),
            ]
            metrics = TrialMetrics(method=method, duration_s=1.0, completed_tasks=k + (method == "proactive"))
            repo.finish_trial(t.id, status="completed", metrics=metrics, events=events)


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    tmp: Path = tmp_path_factory.mktemp("fuzz")
    s = Settings(
        _env_file=None,
        data_dir=tmp,
        api_token=TOKEN,
        database_url=f"sqlite:///{(tmp / 'fuzz.db').as_posix()}",
        robot="sim",
        human_source="sim",
    )
    app = create_app(s, scene=False)
    try:
        schema = schemathesis.openapi.from_asgi("/openapi.json", app)  # starts the lifespan
        _seed(app.state.hrc.repo)
        yield schema
    finally:
        shutdown_lifespans()
    assert app.state.hrc is None  # the lifespan ran its shutdown


def test_every_route_is_fuzzed() -> None:
    """Every HTTP route of every router is in the schema (and so fuzzed above); the WebSockets, which OpenAPI
    cannot describe, are only /api/live and /api/ingest (tests/unit/api/test_live.py)."""
    import importlib
    import pkgutil

    from fastapi.routing import APIRoute, APIWebSocketRoute

    import app.api.routes as routes_pkg
    from app.api.app import API_PREFIX

    routes, sockets = set(), set()
    for info in pkgutil.iter_modules(routes_pkg.__path__):
        router = importlib.import_module(f"app.api.routes.{info.name}").router
        for r in router.routes:
            if isinstance(r, APIRoute) and r.include_in_schema:
                routes |= {(m, API_PREFIX + r.path) for m in r.methods}
            elif isinstance(r, APIWebSocketRoute):
                sockets.add(API_PREFIX + r.path)
    assert routes == {(m, p) for m, p, _ in _operations()}
    assert sockets == {"/api/live", "/api/ingest"}


@pytest.mark.parametrize(("method", "path", "mode"), _operations())
def test_no_server_errors(api_schema: Any, method: str, path: str, mode: GenerationMode) -> None:
    operation = api_schema[path][method]

    @given(case=operation.as_strategy(generation_mode=mode))
    @settings(
        max_examples=MAX_EXAMPLES,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    def fuzz(case: Any) -> None:
        response = case.call(headers=AUTH)
        case.validate_response(response, checks=CHECKS)

    fuzz()
