"""``/api/summary``: the study's Table I per method with paired tests (``hrc report``'s object), as JSON,
CSV, Markdown and box plots."""

from __future__ import annotations

import hashlib
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import PlainTextResponse, Response

from app.api.deps import RepoDep
from app.api.schemas import AUTH_RESPONSES, MAX_ID
from app.study.repository import StudyRepository

router = APIRouter(prefix="/summary", tags=["summary"], responses=AUTH_RESPONSES)

SessionQuery = Annotated[
    int | None, Query(ge=1, le=MAX_ID, description="only this study session (default: every session)")
]


def _summary(repo: StudyRepository, session_id: int | None) -> dict[str, Any]:
    from app.study.stats import summarize

    return summarize(repo, session_id=session_id)


@router.get("")
def get_summary(repo: RepoDep, session_id: SessionQuery = None) -> dict[str, Any]:
    """Per method (``proactive``, ``reactive``): mean, sd and n of every metric over participants; per metric
    the paired test (``tests``) and its p-value (``p_values``); completed trials only."""
    return _summary(repo, session_id)


@router.get("/table.csv", response_class=PlainTextResponse, responses={200: {"content": {"text/csv": {}}}})
def summary_csv(repo: RepoDep, session_id: SessionQuery = None) -> PlainTextResponse:
    """The summary as CSV: one row per metric."""
    from app.study.stats import csv_table

    return PlainTextResponse(
        csv_table(_summary(repo, session_id)),
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": 'attachment; filename="summary.csv"'},
    )


@router.get(
    "/table.md", response_class=PlainTextResponse, responses={200: {"content": {"text/markdown": {}}}}
)
def summary_markdown(repo: RepoDep, session_id: SessionQuery = None) -> PlainTextResponse:
    """The summary as a Markdown table (Table I and the paired tests)."""
    from app.study.stats import markdown_table

    return PlainTextResponse(
        markdown_table(_summary(repo, session_id)), media_type="text/markdown; charset=utf-8"
    )


#: Rendered box plots by (session, data fingerprint): a plot is drawn again only when the data changed.
_PLOT_CACHE: OrderedDict[tuple[int | None, str], bytes] = OrderedDict()
_PLOT_CACHE_SIZE = 8
_PLOT_LOCK = threading.Lock()


def _fingerprint(rows: list[dict[str, Any]]) -> str:
    return hashlib.sha256(repr(rows).encode("utf-8")).hexdigest()


@router.get("/boxplots.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def summary_boxplots(repo: RepoDep, session_id: SessionQuery = None) -> Response:
    """Box plots of the per-participant values of both methods, one panel per metric (PNG)."""
    from app.study.stats import box_plots, summarize_rows

    rows = repo.metrics_rows(session_id=session_id, status="completed")
    key = (session_id, _fingerprint(rows))
    with _PLOT_LOCK:
        data = _PLOT_CACHE.get(key)
        if data is None:
            with tempfile.TemporaryDirectory(prefix="hrc-plots-") as tmp:
                path = box_plots(rows, Path(tmp) / "boxplots.png", summary=summarize_rows(rows))
                data = path.read_bytes()
            _PLOT_CACHE[key] = data
            while len(_PLOT_CACHE) > _PLOT_CACHE_SIZE:
                _PLOT_CACHE.popitem(last=False)
        else:
            _PLOT_CACHE.move_to_end(key)
    return Response(data, media_type="image/png", headers={"Cache-Control": "no-store"})
