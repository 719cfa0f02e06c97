"""``/api/export/{participants,trials,metrics,events}.csv``: every study record as CSV (UTF-8, header row,
ISO 8601 times), the same files as ``hrc export``."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from fastapi.responses import PlainTextResponse

from app.api.deps import RepoDep
from app.api.schemas import AUTH_RESPONSES, MAX_ID

router = APIRouter(prefix="/export", tags=["export"], responses=AUTH_RESPONSES)

CSV_RESPONSE = {200: {"content": {"text/csv": {}}, "description": "the table as a CSV download"}}
SessionFilter = Annotated[int | None, Query(ge=1, le=MAX_ID, description="only this study session")]
TrialFilter = Annotated[int | None, Query(ge=1, le=MAX_ID, description="only this trial")]


def _csv(text: str, name: str) -> PlainTextResponse:
    return PlainTextResponse(
        text,
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{name}.csv"', "Cache-Control": "no-store"},
    )


@router.get("/participants.csv", response_class=PlainTextResponse, responses=CSV_RESPONSE)
def export_participants(repo: RepoDep) -> PlainTextResponse:
    """Participants: one row each."""
    from app.study.export import participants_csv

    return _csv(participants_csv(repo), "participants")


@router.get("/trials.csv", response_class=PlainTextResponse, responses=CSV_RESPONSE)
def export_trials(repo: RepoDep, session_id: SessionFilter = None) -> PlainTextResponse:
    """Trials: one row each, with their settings as JSON."""
    from app.study.export import trials_csv

    return _csv(trials_csv(repo, session_id=session_id), "trials")


@router.get("/metrics.csv", response_class=PlainTextResponse, responses=CSV_RESPONSE)
def export_metrics(repo: RepoDep, session_id: SessionFilter = None) -> PlainTextResponse:
    """Trial metrics: one row per trial that has them."""
    from app.study.export import metrics_csv

    return _csv(metrics_csv(repo, session_id=session_id), "metrics")


@router.get("/events.csv", response_class=PlainTextResponse, responses=CSV_RESPONSE)
def export_events(
    repo: RepoDep, session_id: SessionFilter = None, trial_id: TrialFilter = None
) -> PlainTextResponse:
    """Trial events: one row each (time since the trial started, kind, payload as JSON)."""
    from app.study.export import events_csv

    return _csv(events_csv(repo, trial_id=trial_id, session_id=session_id), "events")
