"""``/api/participants``: study participants (pseudonymous codes), and their counterbalanced method order."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Response, status

from app.api.deps import RepoDep
from app.api.schemas import (
    AUTH_RESPONSES,
    CONFLICT,
    NOT_FOUND,
    LimitQuery,
    MethodOrderRead,
    OffsetQuery,
    ParticipantIdPath,
)
from app.study.repository import ConflictError
from app.study.schemas import ParticipantCreate, ParticipantRead, ParticipantUpdate

router = APIRouter(prefix="/participants", tags=["participants"], responses=AUTH_RESPONSES)


@router.get("", response_model=list[ParticipantRead])
def list_participants(
    repo: RepoDep, offset: OffsetQuery = 0, limit: LimitQuery = 1000
) -> list[ParticipantRead]:
    """Participants in id order."""
    return repo.list_participants(offset=offset, limit=limit)


@router.post("", response_model=ParticipantRead, status_code=status.HTTP_201_CREATED, responses={**CONFLICT})
def create_participant(body: ParticipantCreate, repo: RepoDep) -> ParticipantRead:
    """Add a participant; 409 when the code is taken."""
    return repo.create_participant(body)


@router.get("/{participant_id}", response_model=ParticipantRead, responses={**NOT_FOUND})
def get_participant(participant_id: ParticipantIdPath, repo: RepoDep) -> ParticipantRead:
    return repo.get_participant(participant_id)


@router.patch("/{participant_id}", response_model=ParticipantRead, responses={**NOT_FOUND, **CONFLICT})
def update_participant(
    participant_id: ParticipantIdPath, body: ParticipantUpdate, repo: RepoDep
) -> ParticipantRead:
    """Change the fields present in the body; 409 when the new code is taken."""
    try:
        return repo.update_participant(participant_id, body)
    except ValueError as exc:  # e.g. code set to null
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(exc)) from exc


@router.delete(
    "/{participant_id}", status_code=status.HTTP_204_NO_CONTENT, responses={**NOT_FOUND, **CONFLICT}
)
def delete_participant(
    participant_id: ParticipantIdPath,
    repo: RepoDep,
    with_trials: Annotated[
        bool, Query(description="also delete the participant's trials and records")
    ] = False,
) -> Response:
    """Delete a participant; 409 if they have trials, unless ``with_trials=true``."""
    try:
        repo.delete_participant(participant_id, with_trials=with_trials)
    except ConflictError:  # the repository's message names its Python argument; this names the query
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            f"participant {participant_id} has trials; to delete them and their records too: "
            f"DELETE /api/participants/{participant_id}?with_trials=true",
        ) from None
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.get("/{participant_id}/method-order", response_model=MethodOrderRead, responses={**NOT_FOUND})
def method_order(participant_id: ParticipantIdPath, repo: RepoDep) -> MethodOrderRead:
    """The counterbalanced order of the two methods for this participant."""
    return MethodOrderRead(participant_id=participant_id, methods=repo.suggest_method_order(participant_id))
