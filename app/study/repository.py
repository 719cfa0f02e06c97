"""The study repository: every read and write of the study records goes through :class:`StudyRepository`.

It returns pydantic ``*Read`` models (``app.study.schemas``), never ORM objects, and opens one short
transaction per call, so it can be shared between threads (the API's request handlers, the runtime's trial
listener, an :class:`EventWriter`'s flusher).

Typical life of a trial (live or headless)::

    repo = StudyRepository(make_engine(url))
    trial = repo.create_trial(participant_id=p.id, method="proactive", session_id=s.id, seed=7)
    with repo.event_writer(trial.id) as events:   # batched, flushed at least once a second and on close
        events.write(TrialEvent(t=0.0, kind="trial_started", payload={...}))
    repo.finish_trial(trial.id, status="completed", metrics=metrics)
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, is_dataclass
from datetime import datetime
from typing import Any, TypeVar

import numpy as np
from sqlalchemy import Engine, delete, func, insert, select, update
from sqlalchemy.exc import IntegrityError, SQLAlchemyError
from sqlalchemy.orm import Session, joinedload, sessionmaker

from app.cell.bodies import recorded_bodies
from app.control.metrics import METHODS, TrialEvent, TrialMetrics
from app.control.supervisor_types import TIME_BUDGET
from app.study.db import session_factory
from app.study.models import (
    METRIC_COLUMNS,
    Participant,
    RecordedFrame,
    StudySession,
    Trial,
    TrialEventRow,
    TrialMetricsRow,
    utcnow,
)
from app.study.schemas import (
    FinalStatus,
    Method,
    ParticipantCreate,
    ParticipantRead,
    ParticipantUpdate,
    StudySessionCreate,
    StudySessionRead,
    StudySessionUpdate,
    TrialCreate,
    TrialEventRead,
    TrialMetricsRead,
    TrialRead,
    TrialStatus,
)

log = logging.getLogger(__name__)

INTERRUPTED_REASON = (
    "interrupted: the process that ran the trial ended before the trial finished (killed or crashed); "
    "its metrics, recorded motion and events end at its last checkpoint (ended_at)"
)
#: Settings fields never stored in a trial's settings snapshot.
SECRET_SETTINGS: frozenset[str] = frozenset({"api_token"})
DEFAULT_CHUNK_FRAMES = 300  # 10 s at 30 Hz per recorded_frames row


_RowT = TypeVar("_RowT")


class StudyError(Exception):
    """Base class of the repository's errors."""


class NotFoundError(StudyError, LookupError):
    """A participant, session or trial with that id does not exist."""


class ConflictError(StudyError):
    """The change conflicts with stored data (a duplicate participant code, a participant with trials)."""


class TrialStateError(StudyError):
    """The trial is not in a state that allows the change (e.g. finishing a trial that already ended)."""


def settings_snapshot(settings: Any) -> dict[str, Any]:
    """A JSON-friendly snapshot of ``settings`` (a pydantic model or a mapping) without secrets."""
    if hasattr(settings, "model_dump"):
        data = settings.model_dump(mode="json")
    else:
        data = dict(settings)
    return {k: v for k, v in data.items() if k not in SECRET_SETTINGS}


def json_safe(value: Any) -> Any:
    """``value`` with numpy scalars and arrays turned into Python ones and non-finite floats into None
    (PostgreSQL's JSON has no NaN or Infinity)."""
    if isinstance(value, Mapping):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True)
class RecordedFrames:
    """Frames of a trial for replay, at the camera rate.

    Attributes:
        t: (T,) seconds since the trial started, non-decreasing.
        q: (T, 6) robot joint positions (rad).
        skeleton: (T, B, J, 3) every tracked body's joint positions in the world frame (m), NaN in the body
            slots a frame does not use (:mod:`app.cell.bodies`), or None when none was recorded. A
            single-body array (T, J, 3) (NaN rows where nobody was seen) is taken as one slot, id 0.
        body_ids: (T, B) the tracker's id of each body slot, -1 where unused (None: the single-body
            layout; filled in on construction).
    """

    t: np.ndarray
    q: np.ndarray
    skeleton: np.ndarray | None = None
    body_ids: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=np.float64)
        q = np.asarray(self.q, dtype=np.float32)
        if t.ndim != 1 or t.size == 0:
            raise ValueError(f"frames t must be (T,) with T > 0, got shape {t.shape}")
        if q.shape != (t.size, 6):
            raise ValueError(f"frames q must be (T, 6) = ({t.size}, 6), got {q.shape}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "q", q)
        if self.skeleton is not None:
            sk, ids = recorded_bodies(self.skeleton, self.body_ids)
            if sk.shape[0] != t.size:
                raise ValueError(f"frames skeleton must have T = {t.size} frames, got {sk.shape}")
            object.__setattr__(self, "skeleton", sk)
            object.__setattr__(self, "body_ids", ids)

    def __len__(self) -> int:
        return int(self.t.size)


#: The metrics that may be missing, stored as NULL, and what a missing one reads as in :class:`TrialMetrics`:
#: a separation never measured (no person seen, a robot that never moved) is infinite; the time budget of a
#: trial stored before it was recorded and the arrival errors of a trial without arrivals (or stored before
#: they were recorded) are NaN (unknown); the count of arrivals of a trial stored before it was recorded is
#: 0. A non-finite float is stored as NULL only for these.
NULLABLE_METRICS: dict[str, float | int] = {
    "min_separation_m": math.inf,
    "min_separation_moving_m": math.inf,
    **{f"budget_{k}_s": math.nan for k in TIME_BUDGET},
    "arrivals": 0,
    "arrival_error_median_abs_s": math.nan,
    "arrival_error_bias_s": math.nan,
    "median_plan_s": math.nan,
}


def _metrics_values(metrics: TrialMetrics | Mapping[str, Any]) -> dict[str, Any]:
    """The stored columns of ``metrics`` (non-finite min separation -> None)."""
    data = asdict(metrics) if is_dataclass(metrics) and not isinstance(metrics, type) else dict(metrics)
    unknown = set(data) - set(METRIC_COLUMNS) - {"method", "stop_replans_per_task", "online_replans_per_task"}
    if unknown:
        log.warning("trial metrics fields %s have no database column and are not stored", sorted(unknown))
    missing = [c for c in METRIC_COLUMNS if c not in data]
    if missing:
        raise ValueError(f"trial metrics lack the fields {missing}; pass a complete TrialMetrics")
    values: dict[str, Any] = {}
    for c in METRIC_COLUMNS:
        v = data[c]
        if isinstance(v, (float, np.floating)):
            v = float(v)
            if not math.isfinite(v):
                if c not in NULLABLE_METRICS:
                    allowed = sorted(NULLABLE_METRICS)
                    raise ValueError(f"trial metric {c} is {v}; only {allowed} may be non-finite")
                v = None
        elif isinstance(v, np.integer):
            v = int(v)
        values[c] = v
    return values


def _participant_read(p: Participant) -> ParticipantRead:
    return ParticipantRead.model_validate(p)


def _trial_read(t: Trial) -> TrialRead:
    # While a trial runs, its row holds the last checkpoint (metrics so far, ended_at = when): not shown.
    running = t.status == "running"
    return TrialRead(
        id=t.id,
        participant_id=t.participant_id,
        participant_code=t.participant.code,
        session_id=t.session_id,
        method=t.method,  # type: ignore[arg-type]
        order_index=t.order_index,
        seed=t.seed,
        duration_s=t.duration_s,
        settings=t.settings or {},
        started_at=t.started_at,
        ended_at=None if running else t.ended_at,
        status=t.status,  # type: ignore[arg-type]
        abort_reason=t.abort_reason,
        metrics=TrialMetricsRead.model_validate(t.metrics) if t.metrics is not None and not running else None,
    )


def _frame_chunks(frames: RecordedFrames, trial_id: int, chunk_frames: int) -> list[dict[str, Any]]:
    rows = []
    n_joints = 0 if frames.skeleton is None else int(frames.skeleton.shape[2])
    n_bodies = None if frames.skeleton is None else int(frames.skeleton.shape[1])
    for k, start in enumerate(range(0, len(frames), chunk_frames)):
        sl = slice(start, start + chunk_frames)
        t = frames.t[sl]
        rows.append(
            {
                "trial_id": trial_id,
                "chunk_index": k,
                "n_frames": int(t.size),
                "n_joints": n_joints,
                "t": t.astype("<f8").tobytes(),
                "q": frames.q[sl].astype("<f4").tobytes(),
                "skeleton": None if frames.skeleton is None else frames.skeleton[sl].astype("<f4").tobytes(),
                "n_bodies": n_bodies,
                "body_ids": None if frames.body_ids is None else frames.body_ids[sl].astype("<i4").tobytes(),
            }
        )
    return rows


class StudyRepository:
    """Typed access to the study database. Thread-safe: each call uses its own short session.

    Args:
        engine: From :func:`app.study.db.make_engine`; the schema must be at head
            (:func:`app.study.db.upgrade_to_head`).
    """

    def __init__(self, engine: Engine) -> None:
        self._engine = engine
        self._sessions: sessionmaker[Session] = session_factory(engine)

    @property
    def engine(self) -> Engine:
        return self._engine

    def session(self) -> Session:
        """A new ORM session (for queries the repository does not offer; close it, or use ``with``)."""
        return self._sessions()

    def close(self) -> None:
        """Release the engine's pooled connections."""
        self._engine.dispose()

    # --- participants ---------------------------------------------------------------------------------

    def create_participant(self, data: ParticipantCreate) -> ParticipantRead:
        """Store a new participant.

        Raises:
            ConflictError: a participant with that code exists already.
        """
        with self._sessions() as s:
            p = Participant(**data.model_dump())
            s.add(p)
            try:
                s.commit()
            except IntegrityError as exc:
                s.rollback()
                raise ConflictError(f"a participant with code {data.code!r} exists already") from exc
            return _participant_read(p)

    def get_participant(self, participant_id: int) -> ParticipantRead:
        with self._sessions() as s:
            return _participant_read(self._participant(s, participant_id))

    def get_participant_by_code(self, code: str) -> ParticipantRead | None:
        with self._sessions() as s:
            p = s.scalars(select(Participant).where(Participant.code == code)).one_or_none()
            return None if p is None else _participant_read(p)

    def list_participants(self, *, offset: int = 0, limit: int = 1000) -> list[ParticipantRead]:
        with self._sessions() as s:
            rows = s.scalars(select(Participant).order_by(Participant.id).offset(offset).limit(limit))
            return [_participant_read(p) for p in rows]

    def update_participant(self, participant_id: int, data: ParticipantUpdate) -> ParticipantRead:
        """Change the fields set in ``data``.

        Raises:
            NotFoundError: no such participant. ConflictError: the new code is taken.
        """
        with self._sessions() as s:
            p = self._participant(s, participant_id)
            for k, v in data.model_dump(exclude_unset=True).items():
                if k == "code" and v is None:
                    raise ValueError("a participant code cannot be removed")
                setattr(p, k, "" if (k == "notes" and v is None) else v)
            try:
                s.commit()
            except IntegrityError as exc:
                s.rollback()
                raise ConflictError(f"a participant with code {data.code!r} exists already") from exc
            return _participant_read(p)

    def delete_participant(self, participant_id: int, *, with_trials: bool = False) -> None:
        """Delete a participant; with ``with_trials`` also their trials, metrics, events and frames.

        Raises:
            NotFoundError: no such participant.
            ConflictError: the participant has trials and ``with_trials`` is False.
        """
        with self._sessions() as s:
            p = self._participant(s, participant_id)
            n = s.scalar(select(func.count()).select_from(Trial).where(Trial.participant_id == p.id)) or 0
            if n and not with_trials:
                raise ConflictError(
                    f"participant {p.code!r} has {n} trials; delete them too with with_trials=True"
                )
            s.delete(p)
            s.commit()

    # --- study sessions -------------------------------------------------------------------------------

    def create_session(self, data: StudySessionCreate) -> StudySessionRead:
        with self._sessions() as s:
            row = StudySession(**data.model_dump())
            s.add(row)
            s.commit()
            return StudySessionRead.model_validate(row)

    def get_session(self, session_id: int) -> StudySessionRead:
        with self._sessions() as s:
            return StudySessionRead.model_validate(self._study_session(s, session_id))

    def list_sessions(self, *, offset: int = 0, limit: int = 1000) -> list[StudySessionRead]:
        with self._sessions() as s:
            rows = s.scalars(select(StudySession).order_by(StudySession.id).offset(offset).limit(limit))
            return [StudySessionRead.model_validate(r) for r in rows]

    def resolve_session(self, spec: str | int | None) -> StudySessionRead | None:
        """A session selector as the command line takes it: ``"latest"`` (the newest session, None if there
        is none), ``"all"`` or None (None: no restriction), or a session id.

        Raises:
            NotFoundError: no session with that id. ValueError: ``spec`` is none of these.
        """
        if spec is None or spec == "all":
            return None
        if spec == "latest":
            return self.latest_session()
        try:
            session_id = int(spec)
        except ValueError:
            raise ValueError(f"session must be 'latest', 'all' or a session id, got {spec!r}") from None
        return self.get_session(session_id)

    def latest_session(self) -> StudySessionRead | None:
        """The most recently created study session, or None when there is none."""
        with self._sessions() as s:
            row = s.scalars(select(StudySession).order_by(StudySession.id.desc()).limit(1)).one_or_none()
            return None if row is None else StudySessionRead.model_validate(row)

    def update_session(self, session_id: int, data: StudySessionUpdate) -> StudySessionRead:
        with self._sessions() as s:
            row = self._study_session(s, session_id)
            for k, v in data.model_dump(exclude_unset=True).items():
                if v is None:
                    raise ValueError(f"study session field {k!r} cannot be set to null")
                setattr(row, k, v)
            s.commit()
            return StudySessionRead.model_validate(row)

    def delete_session(self, session_id: int) -> None:
        """Delete a study session; its trials are kept (their ``session_id`` becomes None)."""
        with self._sessions() as s:
            row = self._study_session(s, session_id)
            s.execute(update(Trial).where(Trial.session_id == row.id).values(session_id=None))
            s.delete(row)
            s.commit()

    # --- trials ---------------------------------------------------------------------------------------

    def create_trial(
        self,
        *,
        participant_id: int,
        method: Method,
        session_id: int | None = None,
        order_index: int | None = None,
        seed: int = 0,
        duration_s: float | None = None,
        settings: Mapping[str, Any] | None = None,
        started_at: datetime | None = None,
    ) -> TrialRead:
        """Start a trial (status ``running``, ``started_at`` now unless given).

        ``order_index`` None: the number of trials the participant already has in that session.

        Raises:
            NotFoundError: the participant or the session does not exist.
        """
        data = TrialCreate(
            participant_id=participant_id,
            method=method,
            session_id=session_id,
            order_index=order_index,
            seed=seed,
            duration_s=duration_s,
            settings=dict(settings or {}),
        )
        with self._sessions() as s:
            self._participant(s, data.participant_id)
            if data.session_id is not None:
                self._study_session(s, data.session_id)
            idx = data.order_index
            if idx is None:
                q = select(func.count()).select_from(Trial).where(Trial.participant_id == data.participant_id)
                q = q.where(
                    Trial.session_id == data.session_id
                    if data.session_id is not None
                    else Trial.session_id.is_(None)
                )
                idx = int(s.scalar(q) or 0)
            row = Trial(
                participant_id=data.participant_id,
                session_id=data.session_id,
                method=data.method,
                order_index=idx,
                seed=data.seed,
                duration_s=data.duration_s,
                settings=data.settings,
                started_at=started_at or utcnow(),
                status="running",
            )
            s.add(row)
            s.commit()
            return self._trial_read_by_id(s, row.id)

    def finish_trial(
        self,
        trial_id: int,
        *,
        status: FinalStatus,
        metrics: TrialMetrics | Mapping[str, Any] | None = None,
        reason: str | None = None,
        ended_at: datetime | None = None,
        events: Iterable[TrialEvent] = (),
        frames: RecordedFrames | None = None,
        started_at: datetime | None = None,
    ) -> TrialRead:
        """End a running trial, in one transaction with its metrics and (optionally) remaining events and
        recorded frames. Close the trial's :class:`EventWriter` first so that its events are in.
        ``started_at`` corrects the start time (the headless runner creates trials before they leave the
        queue).

        Raises:
            NotFoundError: no such trial.
            TrialStateError: the trial is not running (it ended already, or was aborted at start-up).
            ValueError: ``metrics`` belong to the other method, or are incomplete.
        """
        if status not in ("completed", "aborted"):
            raise ValueError(f"a trial ends as 'completed' or 'aborted', not {status!r}")
        with self._sessions() as s:
            t = self._trial(s, trial_id)
            if t.status != "running":
                raise TrialStateError(f"trial {trial_id} is {t.status}, not running; it cannot be finished")
            if metrics is not None:
                self._replace_metrics(s, t, metrics)
            self._insert_events(s, trial_id, events)
            if frames is not None:  # the whole recording replaces the checkpoints' chunks
                s.execute(delete(RecordedFrame).where(RecordedFrame.trial_id == trial_id))
                self._insert_frames(s, trial_id, frames, DEFAULT_CHUNK_FRAMES)
            t.status = status
            if started_at is not None:
                t.started_at = started_at
            t.ended_at = ended_at or utcnow()
            t.abort_reason = reason if status == "aborted" else None
            s.commit()
            return self._trial_read_by_id(s, trial_id)

    def checkpoint_trial(
        self,
        trial_id: int,
        *,
        metrics: TrialMetrics | Mapping[str, Any],
        frames: RecordedFrames | None = None,
        at: datetime | None = None,
    ) -> None:
        """Store a running trial's progress, in one transaction: its metrics so far (replacing the last
        checkpoint's), its recorded frames since the last checkpoint (appended as new chunks) and the time
        of the checkpoint in ``ended_at`` (``at``, default now; the API shows neither while the trial runs).
        After a crash, :meth:`abort_interrupted_trials` keeps all three: the trial ends at its last
        checkpoint.

        Raises:
            NotFoundError: no such trial.
            TrialStateError: the trial is not running (it ended meanwhile: nothing is written).
            ValueError: ``metrics`` belong to the other method, or are incomplete.
        """
        with self._sessions() as s:
            t = self._trial(s, trial_id)
            if t.status != "running":
                raise TrialStateError(f"trial {trial_id} is {t.status}, not running; no checkpoint")
            self._replace_metrics(s, t, metrics)
            if frames is not None and len(frames):
                last = s.scalar(
                    select(func.max(RecordedFrame.chunk_index)).where(RecordedFrame.trial_id == trial_id)
                )
                rows = _frame_chunks(frames, trial_id, DEFAULT_CHUNK_FRAMES)
                first = 0 if last is None else int(last) + 1
                for k, row in enumerate(rows):
                    row["chunk_index"] = first + k
                s.execute(insert(RecordedFrame), rows)
            t.ended_at = at or utcnow()
            s.commit()

    def store_keyed_trial(
        self,
        *,
        trial_key: str,
        setting_label: str,
        participant_id: int,
        method: Method,
        session_id: int | None,
        order_index: int,
        seed: int,
        duration_s: float,
        settings: Mapping[str, Any],
        metrics: TrialMetrics | Mapping[str, Any],
        events: Iterable[TrialEvent] = (),
        frames: RecordedFrames | None = None,
        started_at: datetime | None = None,
    ) -> int | None:
        """Store a completed sweep trial with its metrics, events and frames in one transaction, or nothing.

        Returns:
            The new trial's id, or None when a trial with ``trial_key`` is stored already (by this or
            another driver: the unique key decides, also between concurrent writers).
        """
        m_method = metrics.get("method") if isinstance(metrics, Mapping) else metrics.method
        if m_method is not None and m_method != method:
            raise ValueError(f"metrics of a {m_method} trial given for the {method} trial {trial_key!r}")
        with self._sessions() as s:
            row = Trial(
                participant_id=participant_id,
                session_id=session_id,
                method=method,
                order_index=order_index,
                seed=seed,
                duration_s=duration_s,
                settings=dict(settings),
                started_at=started_at or utcnow(),
                ended_at=utcnow(),
                status="completed",
                trial_key=trial_key,
                setting_label=setting_label,
            )
            s.add(row)
            try:
                s.flush()
                s.add(TrialMetricsRow(trial_id=row.id, **_metrics_values(metrics)))
                self._insert_events(s, row.id, events)
                if frames is not None:
                    self._insert_frames(s, row.id, frames, DEFAULT_CHUNK_FRAMES)
                s.commit()
            except IntegrityError:
                s.rollback()
                if self.stored_trial_keys([trial_key]):
                    return None
                raise
            return row.id

    def stored_trial_keys(self, keys: Iterable[str] | None = None, *, prefix: str | None = None) -> set[str]:
        """The trial keys stored already: those of ``keys``, or every key starting with ``prefix``."""
        with self._sessions() as s:
            q = select(Trial.trial_key).where(Trial.trial_key.is_not(None))
            if keys is not None:
                wanted = list(keys)
                if not wanted:
                    return set()
                q = q.where(Trial.trial_key.in_(wanted))
            if prefix is not None:
                q = q.where(Trial.trial_key.startswith(prefix, autoescape=True))
            return {k for k in s.scalars(q) if k is not None}

    def get_trial(self, trial_id: int) -> TrialRead:
        """One trial with its metrics (None while running).

        Raises:
            NotFoundError: no such trial.
        """
        with self._sessions() as s:
            return self._trial_read_by_id(s, trial_id)

    def list_trials(
        self,
        *,
        participant_id: int | None = None,
        session_id: int | None = None,
        method: Method | None = None,
        status: TrialStatus | None = None,
        offset: int = 0,
        limit: int = 1000,
    ) -> list[TrialRead]:
        """Trials (with metrics) in id order, filtered by the arguments that are not None."""
        q = select(Trial).options(joinedload(Trial.participant), joinedload(Trial.metrics)).order_by(Trial.id)
        if participant_id is not None:
            q = q.where(Trial.participant_id == participant_id)
        if session_id is not None:
            q = q.where(Trial.session_id == session_id)
        if method is not None:
            q = q.where(Trial.method == method)
        if status is not None:
            q = q.where(Trial.status == status)
        with self._sessions() as s:
            return [_trial_read(t) for t in s.scalars(q.offset(offset).limit(limit)).unique()]

    def delete_trial(self, trial_id: int) -> None:
        """Delete a trial with its metrics, events and frames."""
        with self._sessions() as s:
            s.delete(self._trial(s, trial_id))
            s.commit()

    def abort_interrupted_trials(self, *, reason: str = INTERRUPTED_REASON) -> list[int]:
        """Mark every trial still ``running`` as ``aborted`` (call once at start-up, before any trial runs:
        a running trial in the database then belongs to a process that was killed). A trial keeps what its
        last checkpoint stored (metrics, frames, events) and ends when that checkpoint was taken; one that
        never reached a checkpoint ends now. Returns their ids."""
        with self._sessions() as s:
            ids = list(s.scalars(select(Trial.id).where(Trial.status == "running").order_by(Trial.id)))
            if ids:
                running = (Trial.id.in_(ids), Trial.status == "running")
                s.execute(update(Trial).where(*running, Trial.ended_at.is_(None)).values(ended_at=utcnow()))
                s.execute(update(Trial).where(*running).values(status="aborted", abort_reason=reason))
                s.commit()
                log.warning("marked %d interrupted trials as aborted: %s", len(ids), ids)
            return ids

    def suggest_method_order(self, participant_id: int) -> list[str]:
        """The counterbalanced order of the two methods for a participant.

        Participants alternate by their index (rank by id, from 0): even -> ``["proactive", "reactive"]``,
        odd -> ``["reactive", "proactive"]``.

        Raises:
            NotFoundError: no such participant.
        """
        with self._sessions() as s:
            self._participant(s, participant_id)
            q = select(func.count()).select_from(Participant).where(Participant.id < participant_id)
            index = int(s.scalar(q) or 0)
        return list(METHODS) if index % 2 == 0 else list(reversed(METHODS))

    # --- events ---------------------------------------------------------------------------------------

    def add_events(self, trial_id: int, events: Iterable[TrialEvent]) -> int:
        """Store events of a trial in one transaction; returns how many. Prefer :meth:`event_writer` for
        events that arrive one by one while the trial runs."""
        with self._sessions() as s:
            n = self._insert_events(s, trial_id, events)
            s.commit()
            return n

    def list_events(
        self, trial_id: int, *, kind: str | None = None, offset: int = 0, limit: int = 10_000
    ) -> list[TrialEventRead]:
        """Events of a trial in time order (then insertion order)."""
        q = select(TrialEventRow).where(TrialEventRow.trial_id == trial_id)
        if kind is not None:
            q = q.where(TrialEventRow.kind == kind)
        q = q.order_by(TrialEventRow.t, TrialEventRow.id).offset(offset).limit(limit)
        with self._sessions() as s:
            return [TrialEventRead.model_validate(e) for e in s.scalars(q)]

    def count_events(self, trial_id: int, *, kind: str | None = None) -> int:
        q = select(func.count()).select_from(TrialEventRow).where(TrialEventRow.trial_id == trial_id)
        if kind is not None:
            q = q.where(TrialEventRow.kind == kind)
        with self._sessions() as s:
            return int(s.scalar(q) or 0)

    def event_writer(
        self,
        trial_id: int,
        *,
        flush_interval_s: float = 1.0,
        max_buffer: int = 10_000,
        on_flush: Callable[[int], None] | None = None,
    ) -> EventWriter:
        """A started :class:`EventWriter` for one trial (use it as a context manager, or call ``close``)."""
        writer = EventWriter(
            self, trial_id, flush_interval_s=flush_interval_s, max_buffer=max_buffer, on_flush=on_flush
        )
        writer.start()
        return writer

    # --- recorded frames ------------------------------------------------------------------------------

    def save_frames(
        self, trial_id: int, frames: RecordedFrames, *, chunk_frames: int = DEFAULT_CHUNK_FRAMES
    ) -> int:
        """Store a trial's frames in chunks of ``chunk_frames``; returns the number of chunks. Replaces
        frames stored before for that trial."""
        if chunk_frames < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
        with self._sessions() as s:
            self._trial(s, trial_id)
            s.execute(delete(RecordedFrame).where(RecordedFrame.trial_id == trial_id))
            n = self._insert_frames(s, trial_id, frames, chunk_frames)
            s.commit()
            return n

    def load_frames(self, trial_id: int) -> RecordedFrames | None:
        """The recorded frames of a trial, or None when none were recorded."""
        q = (
            select(RecordedFrame)
            .where(RecordedFrame.trial_id == trial_id)
            .order_by(RecordedFrame.chunk_index)
        )
        with self._sessions() as s:
            chunks = list(s.scalars(q))
        if not chunks:
            return None
        t = np.concatenate([np.frombuffer(c.t, dtype="<f8") for c in chunks])
        q_arr = np.concatenate([np.frombuffer(c.q, dtype="<f4").reshape(c.n_frames, 6) for c in chunks])
        if not all(c.skeleton is not None for c in chunks):
            return RecordedFrames(t=t, q=q_arr)
        parts = []  # each chunk in the recorded layout; chunks of recordings before revision 0009: one body
        for c in chunks:
            if c.n_bodies is None or c.body_ids is None:
                sk = np.frombuffer(c.skeleton, dtype="<f4").reshape(c.n_frames, c.n_joints, 3)
                parts.append(recorded_bodies(sk))
            else:
                sk = np.frombuffer(c.skeleton, dtype="<f4").reshape(c.n_frames, c.n_bodies, c.n_joints, 3)
                ids = np.frombuffer(c.body_ids, dtype="<i4").reshape(c.n_frames, c.n_bodies)
                parts.append((sk, ids))
        B = max(sk.shape[1] for sk, _ in parts)
        skeleton = np.concatenate(
            [
                np.pad(sk, ((0, 0), (0, B - sk.shape[1]), (0, 0), (0, 0)), constant_values=np.nan)
                for sk, _ in parts
            ]
        )
        body_ids = np.concatenate(
            [np.pad(ids, ((0, 0), (0, B - ids.shape[1])), constant_values=-1) for _, ids in parts]
        )
        return RecordedFrames(t=t, q=q_arr, skeleton=skeleton, body_ids=body_ids)

    # --- analysis -------------------------------------------------------------------------------------

    def metrics_rows(
        self, *, session_id: int | None = None, status: TrialStatus | None = "completed"
    ) -> list[dict[str, Any]]:
        """One flat dict per trial that has metrics: trial and participant fields, every metric column and
        the per-task rates (the input of the statistics and of the metrics CSV)."""
        q = (
            select(Trial, Participant.code, TrialMetricsRow)
            .join(Participant, Participant.id == Trial.participant_id)
            .join(TrialMetricsRow, TrialMetricsRow.trial_id == Trial.id)
            .order_by(Trial.id)
        )
        if session_id is not None:
            q = q.where(Trial.session_id == session_id)
        if status is not None:
            q = q.where(Trial.status == status)
        else:  # a running trial's metrics are its last checkpoint's, not a result
            q = q.where(Trial.status != "running")
        out = []
        with self._sessions() as s:
            for t, code, m in s.execute(q):
                row: dict[str, Any] = {
                    "trial_id": t.id,
                    "participant_id": t.participant_id,
                    "participant_code": code,
                    "session_id": t.session_id,
                    "method": t.method,
                    "order_index": t.order_index,
                    "seed": t.seed,
                    "status": t.status,
                    "started_at": t.started_at,
                    "ended_at": t.ended_at,
                }
                row.update({c: getattr(m, c) for c in METRIC_COLUMNS})
                row["stop_replans_per_task"] = m.stop_replans / max(m.completed_tasks, 1)
                row["online_replans_per_task"] = m.online_replans / max(m.completed_tasks, 1)
                out.append(row)
        return out

    # --- internals ------------------------------------------------------------------------------------

    @staticmethod
    def _get(s: Session, model: type[_RowT], row_id: int, what: str) -> _RowT:
        row = s.get(model, row_id)
        if row is None:
            raise NotFoundError(f"{what} {row_id} does not exist")
        return row

    @classmethod
    def _participant(cls, s: Session, participant_id: int) -> Participant:
        return cls._get(s, Participant, participant_id, "participant")

    @classmethod
    def _study_session(cls, s: Session, session_id: int) -> StudySession:
        return cls._get(s, StudySession, session_id, "study session")

    @classmethod
    def _trial(cls, s: Session, trial_id: int) -> Trial:
        return cls._get(s, Trial, trial_id, "trial")

    @staticmethod
    def _replace_metrics(s: Session, t: Trial, metrics: TrialMetrics | Mapping[str, Any]) -> None:
        m_method = metrics.get("method") if isinstance(metrics, Mapping) else metrics.method
        if m_method is not None and m_method != t.method:
            raise ValueError(f"metrics of a {m_method} trial given for {t.method} trial {t.id}")
        values = _metrics_values(metrics)
        s.execute(delete(TrialMetricsRow).where(TrialMetricsRow.trial_id == t.id))
        s.execute(insert(TrialMetricsRow), [{"trial_id": t.id, **values}])

    def _trial_read_by_id(self, s: Session, trial_id: int) -> TrialRead:
        q = (
            select(Trial)
            .options(joinedload(Trial.participant), joinedload(Trial.metrics))
            .where(Trial.id == trial_id)
            .execution_options(populate_existing=True)
        )
        t = s.scalars(q).unique().one_or_none()
        if t is None:
            raise NotFoundError(f"trial {trial_id} does not exist")
        return _trial_read(t)

    @staticmethod
    def _insert_events(s: Session, trial_id: int, events: Iterable[TrialEvent]) -> int:
        rows = [
            {"trial_id": trial_id, "t": float(e.t), "kind": e.kind, "payload": json_safe(e.payload)}
            for e in events
        ]
        if rows:
            s.execute(insert(TrialEventRow), rows)
        return len(rows)

    @staticmethod
    def _insert_frames(s: Session, trial_id: int, frames: RecordedFrames, chunk_frames: int) -> int:
        rows = _frame_chunks(frames, trial_id, chunk_frames)
        if rows:
            s.execute(insert(RecordedFrame), rows)
        return len(rows)


def open_repository(
    url: str | None = None, *, upgrade: bool = True, abort_interrupted: bool = False
) -> StudyRepository:
    """Open the study database at ``url`` (default: the settings' URL).

    Args:
        upgrade: Migrate the schema to head first (:func:`app.study.db.upgrade_to_head`).
        abort_interrupted: Mark trials left ``running`` by a killed process as ``aborted`` (what the app
            does once at start; not for tools that may run beside a live server).
    """
    from app.study.db import default_database_url, make_engine, upgrade_to_head

    url = url or default_database_url()
    if upgrade:
        upgrade_to_head(url)
    repo = StudyRepository(make_engine(url))
    if abort_interrupted:
        repo.abort_interrupted_trials()
    return repo


class EventWriter:
    """Batched, thread-safe writer of one trial's events.

    :meth:`write` appends to a bounded buffer; a flusher thread (started by :meth:`start`) writes the buffer
    in one transaction at least every ``flush_interval_s`` seconds, and :meth:`close` stops it and writes
    what is left. Only a full buffer makes :meth:`write` write it itself (back-pressure in a burst; the
    buffer then holds at most ``max_buffer`` plus one event per concurrent writer). A failed write keeps
    the batch for the next attempt; while the database stays unreachable the buffer is cut to
    ``max_buffer`` by dropping the oldest events, counted in :attr:`dropped` and logged once. Without
    :meth:`start`, :meth:`write` flushes when due.

    Args:
        repo: Where to write.
        trial_id: The trial the events belong to.
        flush_interval_s: Longest time an event waits in the buffer while the database is reachable.
        max_buffer: Buffer bound (events).
        clock: Monotonic clock (s) that decides when a flush is due (tests pass a fake one).
        on_flush: Called after each successful flush with the total number of events written so far.
    """

    def __init__(
        self,
        repo: StudyRepository,
        trial_id: int,
        *,
        flush_interval_s: float = 1.0,
        max_buffer: int = 10_000,
        clock: Callable[[], float] = time.monotonic,
        on_flush: Callable[[int], None] | None = None,
    ) -> None:
        if not 0 < flush_interval_s <= 1.0:
            raise ValueError(f"flush_interval_s must be in (0, 1] s, got {flush_interval_s}")
        if max_buffer < 1:
            raise ValueError(f"max_buffer must be >= 1, got {max_buffer}")
        self._repo = repo
        self.trial_id = trial_id
        self.flush_interval_s = flush_interval_s
        self.max_buffer = max_buffer
        self._clock = clock
        self._on_flush = on_flush
        self._buf: deque[TrialEvent] = deque()
        self._lock = threading.Lock()  # guards the buffer and the counters
        self._flush_lock = threading.Lock()  # one flush at a time: keeps the order of events
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_flush = clock()
        self._closed = False
        self._overflowing = False
        self._last_write_failed = False
        self.written = 0
        self.dropped = 0
        self.failed_flushes = 0

    @property
    def pending(self) -> int:
        """Events waiting in the buffer."""
        with self._lock:
            return len(self._buf)

    def start(self) -> EventWriter:
        """Start the flusher thread (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(
                target=self._run, name=f"event-writer-{self.trial_id}", daemon=True
            )
            self._thread.start()
        return self

    def write(self, event: TrialEvent) -> None:
        """Queue one event (never blocks on the database).

        Raises:
            TrialStateError: the writer was closed.
        """
        self.write_many((event,))

    def write_many(self, events: Sequence[TrialEvent]) -> None:
        """Queue several events in order. When the buffer is full, the caller writes it (back-pressure for a
        burst, a few ms); only when that write fails are the oldest events beyond the bound dropped."""
        if self._closed:
            raise TrialStateError(f"the event writer of trial {self.trial_id} is closed")
        with self._lock:
            self._buf.extend(events)
            full = len(self._buf) >= self.max_buffer
        if full:
            self.flush()
            if self._last_write_failed:
                self._enforce_bound()
        elif self._thread is None:
            self.maybe_flush()

    def _enforce_bound(self) -> None:
        with self._lock:
            lost = 0
            while len(self._buf) > self.max_buffer:
                self._buf.popleft()
                lost += 1
            self.dropped += lost
            first = lost > 0 and not self._overflowing
            self._overflowing = self._overflowing or lost > 0
        if first:
            log.error(
                "event buffer of trial %d is full and the database cannot be written: dropping the oldest "
                "events (counted in EventWriter.dropped) until a write succeeds",
                self.trial_id,
            )

    def maybe_flush(self, now: float | None = None) -> int:
        """Flush if ``flush_interval_s`` has passed since the last flush or the buffer is full."""
        now = self._clock() if now is None else now
        with self._lock:
            due = now - self._last_flush >= self.flush_interval_s or len(self._buf) >= self.max_buffer
        return self.flush(now=now) if due else 0

    def flush(self, *, now: float | None = None) -> int:
        """Write the buffered events now, in one transaction; returns how many were written (0 on a
        database error, after which the events stay buffered for the next attempt)."""
        with self._flush_lock:
            with self._lock:
                batch = list(self._buf)
                self._buf.clear()
                self._last_flush = self._clock() if now is None else now
            if not batch:
                return 0
            try:
                self._repo.add_events(self.trial_id, batch)
            except SQLAlchemyError as exc:
                with self._lock:
                    self.failed_flushes += 1
                    self._last_write_failed = True
                    self._buf.extendleft(reversed(batch))
                self._enforce_bound()
                log.error(
                    "writing %d events of trial %d failed (kept for retry): %s",
                    len(batch),
                    self.trial_id,
                    exc,
                )
                return 0
            with self._lock:
                self.written += len(batch)
                total = self.written
                self._overflowing = False
                self._last_write_failed = False
        if self._on_flush is not None:
            self._on_flush(total)
        return len(batch)

    def close(self, *, timeout_s: float = 10.0) -> None:
        """Stop the flusher and write what is left (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
            if self._thread.is_alive():
                log.error("event writer of trial %d did not stop within %.1f s", self.trial_id, timeout_s)
        self.flush()
        if self.pending:
            log.error("event writer of trial %d closed with %d unwritten events", self.trial_id, self.pending)

    def __enter__(self) -> EventWriter:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                remaining = self.flush_interval_s - (self._clock() - self._last_flush)
            if remaining > 0 and self._wake.wait(timeout=remaining):
                self._wake.clear()
            if self._stop.is_set():
                break
            try:
                self.maybe_flush()
            except Exception:  # the thread must survive anything a callback raises
                log.exception("event writer of trial %d: flush failed", self.trial_id)
