"""The FastAPI application factory and its lifespan.

``create_app(settings)`` builds the app; nothing starts until the lifespan runs (uvicorn, or
``TestClient`` used as a context manager). At start the lifespan

1. resolves the operator token (environment, token file, or a new one written with mode 0600),
2. migrates the study database to head and marks trials left ``running`` by a killed process as aborted,
3. starts the trial recorder thread, the runtime's threads, the live-snapshot broadcaster and, when the UI
   package provides it, the viser scene on ``HRC_VISER_PORT``;

and at shutdown it stops them in the safe order: the runtime (and with it the robot) first, then the recorder
drains and the database is flushed and closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fastapi import FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, RedirectResponse

from app.api.auth import ensure_api_token
from app.api.deps import ApiContext
from app.api.live_hub import LiveHub, LiveLimits
from app.api.recorder import Checkpoint, TrialRecorder
from app.api.version import app_version
from app.config import Settings
from app.control.metrics import TrialMetrics
from app.control.runtime import Runtime, TrialAlreadyRunning
from app.study.repository import (
    ConflictError,
    NotFoundError,
    RecordedFrames,
    StudyRepository,
    TrialStateError,
)

if TYPE_CHECKING:  # the 3D view is optional (viser); it is imported when it starts
    from sqlalchemy.engine import Engine

    from app.ui.scene import CellScene

logger = logging.getLogger(__name__)

API_PREFIX = "/api"
UI_STATIC_DIR = Path(__file__).resolve().parents[1] / "ui" / "static"

OPENAPI_TAGS = [
    {"name": "health", "description": "Liveness (no token needed)."},
    {"name": "participants", "description": "Study participants (pseudonymous codes)."},
    {"name": "sessions", "description": "Study sessions that group trials."},
    {"name": "trials", "description": "Start, stop and read trials; one trial runs at a time."},
    {"name": "robot", "description": "Robot and supervisor state, E-stop and reset."},
    {"name": "summary", "description": "The study's Table I and paired tests."},
    {"name": "export", "description": "CSV export of every record."},
]


class StopOnce:
    """Call ``fn`` once, from whichever thread asks first (a signal's helper thread or the lifespan); later
    callers wait (bounded) until that first call has finished."""

    def __init__(self, fn: Callable[[], object], *, name: str, timeout_s: float = 30.0) -> None:
        self._fn = fn
        self._name = name
        self._timeout_s = timeout_s
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._started = False

    def __call__(self) -> None:
        with self._lock:
            first = not self._started
            self._started = True
        if not first:
            if not self._done.wait(self._timeout_s):
                logger.error("%s did not stop within %.0f s", self._name, self._timeout_s)
            return
        try:
            self._fn()
        except Exception:
            logger.exception("%s did not stop cleanly", self._name)
        finally:
            self._done.set()


def _open_repository(settings: Settings) -> tuple[StudyRepository, Engine]:
    """Migrate the database to head and open a repository on it; returns ``(repo, engine)``."""
    from app.study.db import make_engine, upgrade_to_head

    url = settings.resolved_database_url()
    upgrade_to_head(url)
    engine = make_engine(url)
    return StudyRepository(engine), engine


def _make_runtime(settings: Settings) -> Runtime:
    from app.control.engine import EngineOptions

    return Runtime(settings, options=EngineOptions(record_frames=True))  # frames are stored for replay


def _frames_getter(runtime: Runtime) -> Callable[[TrialMetrics], RecordedFrames | None]:
    """``frames_of(metrics)``: the recorded frames of the trial whose result carries ``metrics`` (the
    runtime's ``last_result``), as the study's ``RecordedFrames``; None when not recorded."""

    def frames_of(metrics: TrialMetrics) -> RecordedFrames | None:
        result = getattr(runtime, "last_result", None)
        if result is None or getattr(result, "metrics", None) is not metrics:
            return None
        frames = getattr(result, "frames", None)
        if frames is None or len(frames) == 0:
            return None
        from app.study.runner import frames_from_result

        return frames_from_result(frames)

    return frames_of


def _checkpoint_getter(runtime: Runtime) -> Callable[[int, int], Checkpoint | None] | None:
    """``checkpoint_of(trial_id, first_frame)`` for the recorder, from the runtime's ``checkpoint`` (None
    for a runtime without one)."""
    take = getattr(runtime, "checkpoint", None)
    if take is None:
        return None

    def checkpoint_of(trial_id: int, first_frame: int) -> Checkpoint | None:
        ck = take(trial_id, first_frame=first_frame)
        if ck is None:
            return None
        from app.study.runner import frames_from_result

        return Checkpoint(ck.metrics, frames_from_result(ck.frames), ck.first_frame)

    return checkpoint_of


class ViewerPortInUse(RuntimeError):  # noqa: N818 (reads as the condition it reports)
    """The 3D view's port (``HRC_VISER_PORT``) is held by another program: the server does not start."""


def viewer_port_message(host: str, port: int) -> str:
    """The one line that says the 3D view's port is taken and what to do."""
    return (
        f"the 3D view's port {port} on {host} is in use by another program: stop it, or set HRC_VISER_PORT "
        "(hrc serve --viser-port) to a free port"
    )


def _start_scene(settings: Settings, runtime: Runtime, token: str) -> CellScene | None:
    """Start the viser 3D view when the UI package provides it (viewers need the operator token); None
    (logged) when it cannot start.

    Raises:
        ViewerPortInUse: another program holds ``HRC_VISER_PORT``.
    """
    try:
        from app.ui.scene import CellScene
        from app.ui.viser_server import PortInUse
    except ImportError as exc:
        logger.info("no 3D view: app.ui.scene is not available (%s)", exc)
        return None
    try:
        scene = CellScene(
            runtime,
            settings.load_workcell(),
            port=settings.viser_port,
            host=settings.host,  # the 3D view is reachable where the API is, with the same token
            roadmap=getattr(runtime, "roadmap", None),
            token=token,
        )
        scene.start()
    except PortInUse as exc:
        raise ViewerPortInUse(viewer_port_message(exc.host, exc.port)) from exc
    except Exception:
        logger.exception(
            "the 3D view (viser) could not start on port %d; continuing without it", settings.viser_port
        )
        return None
    logger.info("3D view (viser) on port %d", scene.port)
    return scene


def create_app(
    settings: Settings,
    *,
    runtime: Runtime | None = None,
    repo: StudyRepository | None = None,
    limits: LiveLimits | None = None,
    scene: bool = True,
) -> FastAPI:
    """Build the operator API.

    Args:
        settings: Application settings (``HRC_*``).
        runtime: The live runtime; None builds ``app.control.runtime.Runtime(settings)``. Either way the
            lifespan starts it and stops it.
        repo: The study repository; None migrates ``settings.resolved_database_url()`` to head and opens a
            ``StudyRepository`` on it (its engine is disposed at shutdown; an injected one is left to its
            owner).
        limits: Bounds of the live WebSockets (rates, queue sizes, message size).
        scene: Start the viser 3D view (when ``app.ui.scene`` exists). Tests pass False.

    Returns:
        The app; serve it with uvicorn (one worker) or use ``TestClient(app)`` as a context manager.
    """
    limits = limits or LiveLimits()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        token = ensure_api_token(settings)
        engine = None
        repository = repo
        if repository is None:
            repository, engine = _open_repository(settings)
        abort_interrupted = getattr(repository, "abort_interrupted_trials", None)
        if abort_interrupted is not None:
            ids = abort_interrupted()
            if ids:
                logger.warning("trials %s were left running by an earlier process: marked aborted", list(ids))
        recorder: TrialRecorder | None = None
        hub: LiveHub | None = None
        stop_runtime: StopOnce | None = None
        view = None
        try:
            rt = runtime if runtime is not None else _make_runtime(settings)
            recorder = TrialRecorder(
                repository, frames_of=_frames_getter(rt), checkpoint_of=_checkpoint_getter(rt)
            )
            recorder.start()
            rt.add_event_listener(recorder.on_event)
            rt.add_trial_listener(recorder.on_trial_end)
            hub = LiveHub(rt, limits=limits)
            stop_runtime = StopOnce(rt.stop, name="runtime")
            rt.start()
            hub.start(asyncio.get_running_loop())
            if scene:
                view = _start_scene(settings, rt, token.value)
            app.state.hrc = ApiContext(
                settings=settings,
                token=token.value,
                runtime=rt,
                repo=repository,
                hub=hub,
                recorder=recorder,
                viser_port=None if view is None else int(view.port),
            )
            app.state.stop_runtime = stop_runtime
            logger.info("operator API ready (token from %s)", token.source)
            yield
        finally:
            app.state.hrc = None
            if hub is not None:
                hub.stop()
            if view is not None:
                with contextlib.suppress(Exception):
                    view.stop()
            if stop_runtime is not None:
                stop_runtime()  # the robot stops first: a running trial ends (aborted) through the recorder
            app.state.stop_runtime = None
            if recorder is not None:
                recorder.close()  # drain: results and events into the database, then flush
            if engine is not None:
                engine.dispose()
            logger.info("operator API stopped")

    app = FastAPI(
        title="hrc-proactive operator API",
        version=app_version(),
        summary="Proactive human-aware motion planning for a UR5e: trials, robot, study records, live state.",
        docs_url="/docs",
        redoc_url=None,
        openapi_url="/openapi.json",
        openapi_tags=OPENAPI_TAGS,
        lifespan=lifespan,
    )
    app.state.hrc = None
    app.state.stop_runtime = None
    app.state.settings = settings
    _install_error_handlers(app)
    _include_routes(app)
    _mount_ui(app)
    _document_errors_as_json(app)
    return app


#: Errors every operation may answer beside its own, documented in the OpenAPI schema.
COMMON_ERRORS: dict[str, str] = {
    "503": "the server is starting or stopping, or the study database is unreachable; retry",
}
#: The error of an operation with a request body whose bytes are not JSON text (FastAPI's own reply).
BAD_BODY_ERROR = "the request body cannot be parsed (not JSON text)"


def _document_errors_as_json(app: FastAPI) -> None:
    """Make the OpenAPI schema say what errors really are: every error response (4xx, 5xx) is JSON, also on
    routes whose success is CSV, Markdown or PNG (FastAPI documents their errors in the route's own media
    type); an operation with a body may answer 400 (unparseable body); every operation may answer 503."""
    build = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        schema = build()
        error_ref = {"$ref": "#/components/schemas/ErrorRead"}
        for operations in schema.get("paths", {}).values():
            for op in operations.values():
                responses = op.setdefault("responses", {})
                for code, response in responses.items():
                    if code[:1] in ("4", "5") and "content" in response:
                        found = [c["schema"] for c in response["content"].values() if "schema" in c]
                        response["content"] = {
                            "application/json": {"schema": found[0] if found else error_ref}
                        }
                if "requestBody" in op:
                    responses.setdefault(
                        "400",
                        {
                            "description": BAD_BODY_ERROR,
                            "content": {"application/json": {"schema": error_ref}},
                        },
                    )
                for code, description in COMMON_ERRORS.items():
                    responses.setdefault(
                        code,
                        {"description": description, "content": {"application/json": {"schema": error_ref}}},
                    )
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _include_routes(app: FastAPI) -> None:
    from app.api.deps import AuthDep
    from app.api.routes import export, health, live, participants, robot, sessions, summary, trials

    app.include_router(health.router, prefix=API_PREFIX)
    for module in (participants, sessions, trials, robot, summary, export):
        app.include_router(module.router, prefix=API_PREFIX, dependencies=[AuthDep])
    app.include_router(live.router, prefix=API_PREFIX)


def _mount_ui(app: FastAPI) -> None:
    if (UI_STATIC_DIR / "index.html").is_file():
        from fastapi.staticfiles import StaticFiles

        app.mount("/", StaticFiles(directory=UI_STATIC_DIR, html=True), name="ui")
        return

    @app.get("/", include_in_schema=False)
    def _root() -> RedirectResponse:
        return RedirectResponse("/docs")


def _format_loc(loc: tuple[Any, ...] | list[Any]) -> str:
    return ".".join(str(p) for p in loc) or "<request>"


#: Exceptions of the study layer and the runtime that a request may raise, and the HTTP status each one is
#: answered with (the body's ``detail`` is the exception's message). A route that can say more catches its
#: exception first (``POST /trials`` names the trial that runs). Subclasses map with their base class.
ERROR_STATUS: dict[type[Exception], int] = {
    NotFoundError: status.HTTP_404_NOT_FOUND,
    ConflictError: status.HTTP_409_CONFLICT,
    TrialStateError: status.HTTP_409_CONFLICT,
    TrialAlreadyRunning: status.HTTP_409_CONFLICT,
}


def _status_handler(code: int) -> Callable[[Request, Exception], Any]:
    """An exception handler that answers ``code`` with the exception's message as ``detail``."""

    async def handler(_request: Request, exc: Exception) -> JSONResponse:
        return JSONResponse(status_code=code, content={"detail": str(exc)})

    return handler


def _install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [
            {
                "loc": [str(p) for p in e.get("loc", ())],
                "msg": str(e.get("msg", "")),
                "type": str(e.get("type", "")),
            }
            for e in exc.errors()
        ]
        detail = "; ".join(f"{_format_loc(e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
        return JSONResponse(
            status_code=status.HTTP_422_UNPROCESSABLE_CONTENT,
            content={"detail": f"invalid request: {detail}", "errors": errors},
        )

    from sqlalchemy.exc import DataError, OperationalError

    for exc_class, code in ERROR_STATUS.items():
        app.add_exception_handler(exc_class, _status_handler(code))

    @app.exception_handler(DataError)
    async def _bad_value(request: Request, exc: DataError) -> JSONResponse:
        # e.g. PostgreSQL refuses NUL characters in text: the value, not the server, is at fault
        logger.info("database refused a value on %s %s: %s", request.method, request.url.path, exc.orig)
        return JSONResponse(
            status_code=status.HTTP_422_UNPROCESSABLE_CONTENT,
            content={"detail": f"the database cannot store a value of this request: {exc.orig}"},
        )

    @app.exception_handler(OperationalError)
    async def _database_down(request: Request, exc: OperationalError) -> JSONResponse:
        logger.error("database error on %s %s: %s", request.method, request.url.path, exc)
        return JSONResponse(
            status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
            content={"detail": "the study database is not reachable; check HRC_DATABASE_URL and retry"},
        )

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        logger.error("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
        return JSONResponse(
            status_code=status.HTTP_500_INTERNAL_SERVER_ERROR,
            content={"detail": "internal server error; the server log has the details"},
        )
