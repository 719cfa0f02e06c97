"""``GET /api/health`` (no token: for health checks) and ``GET /api/info`` (what a client needs to know)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from app.api.deps import AuthDep, ContextDep
from app.api.schemas import (
    AUTH_RESPONSES,
    MAX_TRIAL_DURATION_S,
    MIN_TRIAL_DURATION_S,
    HealthRead,
    InfoRead,
    PredictorRead,
)
from app.api.version import app_version
from app.control.metrics import METHODS
from app.control.runtime import Runtime
from app.study.repository import StudyRepository

logger = logging.getLogger(__name__)

router = APIRouter(tags=["health"])


def _database_ok(repo: StudyRepository) -> bool:
    engine = getattr(repo, "engine", None)
    if engine is None:
        return True  # a repository without an engine (a test double) has nothing to ping
    from sqlalchemy import text
    from sqlalchemy.exc import SQLAlchemyError

    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except SQLAlchemyError as exc:
        logger.warning("health: the database does not answer: %s", exc)
        return False
    return True


#: A runtime whose newest snapshot is older than this (s) has a stuck or dead frame loop.
STALE_SNAPSHOT_S = 2.0


def _runtime_alive(runtime: Runtime) -> bool:
    """The runtime's loops run: its newest snapshot is recent (frames are published at the camera rate)."""
    clock = getattr(runtime, "clock", None)
    if clock is None:
        return True
    try:
        return clock.now() - float(runtime.snapshot().t) < STALE_SNAPSHOT_S
    except Exception:
        logger.exception("health: the runtime's snapshot cannot be read")
        return False


@router.get(
    "/health",
    response_model=HealthRead,
    responses={503: {"model": HealthRead, "description": "the database or the runtime is down"}},
)
def health(request: Request) -> HealthRead | JSONResponse:
    """Liveness and readiness: 200 when the runtime runs and the database answers, else 503."""
    ctx = getattr(request.app.state, "hrc", None)
    if ctx is None:
        body = HealthRead(status="degraded", version=app_version(), runtime="stopped", database="error")
        return JSONResponse(body.model_dump(), status_code=503)
    db_ok = _database_ok(ctx.repo)
    running = _runtime_alive(ctx.runtime)
    body = HealthRead(
        status="ok" if db_ok and running else "degraded",
        version=app_version(),
        runtime="running" if running else "stopped",
        database="ok" if db_ok else "error",
    )
    if body.status != "ok":
        return JSONResponse(body.model_dump(), status_code=503)
    return body


@router.get("/info", response_model=InfoRead, dependencies=[AuthDep], responses=AUTH_RESPONSES)
def info(ctx: ContextDep) -> InfoRead:
    """Server facts for clients: the viser port of the 3D view, the cell's configuration, the limits, the
    predictor that runs (its weights file and their SHA-256)."""
    s = ctx.settings
    limits = ctx.hub.limits
    return InfoRead(
        version=app_version(),
        viser_port=ctx.viser_port if ctx.viser_port is not None else s.viser_port,
        robot=s.robot,
        human_source=s.human_source,
        read_only_open=s.read_only_open,
        methods=list(METHODS),
        min_trial_duration_s=MIN_TRIAL_DURATION_S,
        max_trial_duration_s=MAX_TRIAL_DURATION_S,
        live_rate_hz=limits.live_rate_hz,
        ingest_max_bytes=limits.ingest_max_bytes,
        ingest_rate_hz=limits.ingest_rate_hz,
        deadline_s=s.deadline_s,
        anticipate_fetch=s.anticipate_fetch,
        predictor=_predictor(ctx.runtime),
    )


def _predictor(runtime: Runtime) -> PredictorRead | None:
    info = getattr(runtime, "predictor_info", None)
    return None if info is None else PredictorRead(**info.to_json())
