"""``/api/trials``: start a trial (one at a time), stop it, read trials with their metrics and events.

A trial started here is created in the database (status ``running``), then run by the runtime; when the
runtime reports its end, the recorder stores its metrics and events and its final status.
"""

from __future__ import annotations

import logging
import secrets
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, status

from app.api.deps import ContextDep, RepoDep
from app.api.schemas import (
    AUTH_RESPONSES,
    CONFLICT,
    MAX_ID,
    NOT_FOUND,
    LimitQuery,
    Method,
    OffsetQuery,
    TrialDetail,
    TrialIdPath,
    TrialStart,
)
from app.config import Settings
from app.control.runtime import TrialAlreadyRunning
from app.study.schemas import TrialEventRead, TrialRead, TrialStatus

logger = logging.getLogger(__name__)

router = APIRouter(prefix="/trials", tags=["trials"], responses=AUTH_RESPONSES)

#: How long ``POST /trials/{id}/stop`` waits for the stopped trial to be stored before it answers.
STOP_WAIT_S = 5.0
#: Longest wait for the lock that serialises trial starts.
START_LOCK_TIMEOUT_S = 10.0
MAX_EVENTS = 10_000

OptionalId = Annotated[int | None, Query(ge=1, le=MAX_ID)]


def _settings_snapshot(settings: Settings, runtime: Any = None, method: str | None = None) -> dict[str, Any]:
    """The settings a trial runs with, without secrets (token; a database password in the URL), and under
    ``predictor`` the predictor a proactive trial runs (kind, weights file, their SHA-256; null for a
    reactive trial, which holds the current pose)."""
    from sqlalchemy.engine import make_url

    from app.study.repository import settings_snapshot

    snap = settings_snapshot(settings)
    if snap.get("database_url"):
        snap["database_url"] = make_url(snap["database_url"]).render_as_string(hide_password=True)
    info = getattr(runtime, "predictor_info", None)
    if method == "proactive" and info is not None:
        snap["predictor"] = info.to_json()
    elif method is not None:
        snap["predictor"] = None
    return snap


def _running_conflict(trial_id: int) -> HTTPException:
    return HTTPException(
        status.HTTP_409_CONFLICT,
        f"trial {trial_id} is running; stop it first (POST /api/trials/{trial_id}/stop) or wait for its end",
    )


@router.get("", response_model=list[TrialRead])
def list_trials(
    repo: RepoDep,
    participant_id: OptionalId = None,
    session_id: OptionalId = None,
    method: Method | None = None,
    status_: Annotated[TrialStatus | None, Query(alias="status")] = None,
    offset: OffsetQuery = 0,
    limit: LimitQuery = 1000,
) -> list[TrialRead]:
    """Trials in id order, with metrics, filtered by participant, session, method and status."""
    return repo.list_trials(
        participant_id=participant_id,
        session_id=session_id,
        method=method,
        status=status_,
        offset=offset,
        limit=limit,
    )


@router.post(
    "",
    response_model=TrialRead,
    status_code=status.HTTP_201_CREATED,
    responses={**NOT_FOUND, **CONFLICT},
)
def start_trial(body: TrialStart, ctx: ContextDep) -> TrialRead:
    """Start a trial now; 409 naming the running trial if one runs, 404 for an unknown participant/session."""
    runtime, repo = ctx.runtime, ctx.repo
    if not ctx.trial_lock.acquire(timeout=START_LOCK_TIMEOUT_S):
        raise HTTPException(status.HTTP_409_CONFLICT, "another trial is being started; retry in a moment")
    try:
        running = runtime.running_trial_id
        if running is not None:
            raise _running_conflict(running)
        seed = body.seed if body.seed is not None else secrets.randbelow(2**31)
        trial = repo.create_trial(
            participant_id=body.participant_id,
            method=body.method,
            session_id=body.session_id,
            seed=seed,
            duration_s=body.duration_s,
            settings=_settings_snapshot(ctx.settings, runtime, body.method),
        )
        ctx.recorder.begin(trial.id)
        try:
            runtime.start_trial(trial_id=trial.id, method=body.method, duration_s=body.duration_s, seed=seed)
        except TrialAlreadyRunning as exc:
            ctx.recorder.abandon(trial.id, f"not started: {exc}")
            other = runtime.running_trial_id
            raise _running_conflict(other) if other is not None else HTTPException(409, str(exc)) from exc
        except (RuntimeError, ValueError) as exc:
            # the runtime refused (e.g. E-stopped, robot not connected): record why, tell the client
            ctx.recorder.abandon(trial.id, f"not started: {exc}")
            logger.warning("trial %d not started: %s", trial.id, exc)
            raise HTTPException(status.HTTP_409_CONFLICT, f"the runtime cannot start a trial: {exc}") from exc
        logger.info("trial %d started: %s, %.1f s, seed %d", trial.id, body.method, body.duration_s, seed)
        return trial
    finally:
        ctx.trial_lock.release()


@router.get("/{trial_id}", response_model=TrialDetail, responses={**NOT_FOUND})
def get_trial(
    trial_id: TrialIdPath,
    repo: RepoDep,
    events_limit: Annotated[
        int, Query(ge=0, le=MAX_EVENTS, description="most events to include")
    ] = MAX_EVENTS,
) -> TrialDetail:
    """One trial with its metrics (null while it runs) and its events in time order."""
    trial = repo.get_trial(trial_id)
    events = repo.list_events(trial_id, limit=events_limit) if events_limit else []
    total = repo.count_events(trial_id)
    return TrialDetail(**trial.model_dump(), events=events, events_total=total)


@router.get("/{trial_id}/events", response_model=list[TrialEventRead], responses={**NOT_FOUND})
def list_trial_events(
    trial_id: TrialIdPath,
    repo: RepoDep,
    kind: Annotated[str | None, Query(max_length=64)] = None,
    offset: OffsetQuery = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_EVENTS)] = MAX_EVENTS,
) -> list[TrialEventRead]:
    """Events of a trial in time order (optionally of one kind)."""
    repo.get_trial(trial_id)  # 404 for an unknown trial
    return repo.list_events(trial_id, kind=kind, offset=offset, limit=limit)


@router.post("/{trial_id}/stop", response_model=TrialRead, responses={**NOT_FOUND, **CONFLICT})
def stop_trial(trial_id: TrialIdPath, ctx: ContextDep) -> TrialRead:
    """Stop the running trial (the robot stops; the trial is stored as ended by the operator).

    Waits up to a few seconds for the result to be stored and returns the trial; 409 if it is not running.
    """
    trial = ctx.repo.get_trial(trial_id)
    if ctx.runtime.running_trial_id != trial_id:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"trial {trial_id} is not running (status: {trial.status}); nothing to stop",
        )
    ctx.runtime.stop_trial(reason="operator")
    if not ctx.recorder.wait_stored(trial_id, STOP_WAIT_S):
        logger.warning("trial %d: stop requested, result not stored within %.1f s", trial_id, STOP_WAIT_S)
    return ctx.repo.get_trial(trial_id)
