"""Request dependencies: the application context, settings, repository, runtime and the token check.

Routes declare what they need with ``Annotated`` aliases (``SettingsDep``, ``RepoDep``, ``RuntimeDep``,
``ContextDep``); the objects live on ``app.state.hrc`` (an :class:`ApiContext` set up by the lifespan),
never in module globals, so several apps (tests) can live in one process.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from app.api.auth import tokens_match
from app.api.live_hub import LiveHub
from app.api.recorder import TrialRecorder
from app.config import Settings
from app.control.runtime import Runtime
from app.study.repository import StudyRepository


@dataclass
class ApiContext:
    """Everything a request may use, created by the lifespan and stored on ``app.state.hrc``.

    Attributes:
        settings: The application settings.
        token: The operator token (never logged).
        runtime: The live runtime (tests pass a double with the same methods).
        repo: The study repository (tests may pass a double with the same methods).
        hub: The live-snapshot fan-out to WebSocket clients.
        recorder: Writes trial events and results into the repository off the control thread.
        trial_lock: Serialises trial starts so that two concurrent requests cannot both start one.
        viser_port: The port the 3D view is bound to (None: it is not running; clients fall back to the
            configured one).
    """

    settings: Settings
    token: str
    runtime: Runtime
    repo: StudyRepository
    hub: LiveHub
    recorder: TrialRecorder
    trial_lock: threading.Lock = field(default_factory=threading.Lock)
    viser_port: int | None = None


def get_context(request: Request) -> ApiContext:
    """The :class:`ApiContext` of the running app (503 while the app is starting or stopping)."""
    ctx = getattr(request.app.state, "hrc", None)
    if ctx is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "the server is starting or stopping; retry")
    return ctx


ContextDep = Annotated[ApiContext, Depends(get_context)]


def get_settings(ctx: ContextDep) -> Settings:
    """The application settings."""
    return ctx.settings


def get_repo(ctx: ContextDep) -> StudyRepository:
    """The study repository."""
    return ctx.repo


def get_runtime(ctx: ContextDep) -> Runtime:
    """The live runtime."""
    return ctx.runtime


SettingsDep = Annotated[Settings, Depends(get_settings)]
RepoDep = Annotated[StudyRepository, Depends(get_repo)]
RuntimeDep = Annotated[Runtime, Depends(get_runtime)]

_bearer = HTTPBearer(
    auto_error=False,
    description="The operator token (HRC_API_TOKEN, or the one printed at the first start).",
)

#: Methods that only read: open without a token when ``HRC_READ_ONLY_OPEN`` is set.
READ_ONLY_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def require_token(
    request: Request,
    ctx: ContextDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Reject the request with 401 unless it carries the operator token as a bearer token.

    With ``settings.read_only_open`` a GET needs no token. The comparison runs in constant time.
    """
    if ctx.settings.read_only_open and request.method in READ_ONLY_METHODS:
        return
    given = credentials.credentials if credentials is not None else None
    if given is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing operator token: send 'Authorization: Bearer <token>' (HRC_API_TOKEN, or the token "
            "printed at the first start and stored in <data_dir>/api_token)",
            headers={"WWW-Authenticate": "Bearer"},
        )
    if not tokens_match(given, ctx.token):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "invalid operator token",
            headers={"WWW-Authenticate": 'Bearer error="invalid_token"'},
        )


AuthDep = Depends(require_token)
