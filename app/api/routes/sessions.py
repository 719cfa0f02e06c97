"""``/api/sessions``: study sessions that group trials."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response, status

from app.api.deps import RepoDep
from app.api.schemas import AUTH_RESPONSES, NOT_FOUND, LimitQuery, OffsetQuery, SessionIdPath
from app.study.schemas import StudySessionCreate, StudySessionRead, StudySessionUpdate

router = APIRouter(prefix="/sessions", tags=["sessions"], responses=AUTH_RESPONSES)


@router.get("", response_model=list[StudySessionRead])
def list_sessions(repo: RepoDep, offset: OffsetQuery = 0, limit: LimitQuery = 1000) -> list[StudySessionRead]:
    """Study sessions in id order."""
    return repo.list_sessions(offset=offset, limit=limit)


@router.post("", response_model=StudySessionRead, status_code=status.HTTP_201_CREATED)
def create_session(body: StudySessionCreate, repo: RepoDep) -> StudySessionRead:
    return repo.create_session(body)


@router.get("/{session_id}", response_model=StudySessionRead, responses={**NOT_FOUND})
def get_session(session_id: SessionIdPath, repo: RepoDep) -> StudySessionRead:
    return repo.get_session(session_id)


@router.patch("/{session_id}", response_model=StudySessionRead, responses={**NOT_FOUND})
def update_session(session_id: SessionIdPath, body: StudySessionUpdate, repo: RepoDep) -> StudySessionRead:
    """Change the fields present in the body (null is not allowed)."""
    try:
        return repo.update_session(session_id, body)
    except ValueError as exc:  # a field set to null
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)) from exc


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT, responses={**NOT_FOUND})
def delete_session(session_id: SessionIdPath, repo: RepoDep) -> Response:
    """Delete a session; its trials are kept without a session."""
    repo.delete_session(session_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
