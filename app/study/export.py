"""CSV export of the study records: participants, trials, metrics (one row per trial) and events.

Every file is UTF-8 with a header row, comma-separated, LF line ends, RFC 4180 quoting; times are ISO 8601
with the UTC offset (``2026-05-04T09:30:00.123456+00:00``); missing values are empty cells; JSON columns
(``settings_json``, ``payload_json``) hold one JSON object per cell. The files open in pandas
(``pd.read_csv(path, parse_dates=[...])``), R (``read.csv``) and spreadsheets.

``*_csv(repo, ...) -> str`` return one table as text (for the API's download routes);
``write_*_csv(repo, fp, ...)`` stream it into an open text file; :func:`export_all` writes the four files.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from collections.abc import Callable, Iterable
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

from sqlalchemy import func, select

from app.study.models import METRIC_COLUMNS, Participant, StudySession, Trial, TrialEventRow
from app.study.repository import StudyRepository

log = logging.getLogger(__name__)

PARTICIPANT_COLUMNS: tuple[str, ...] = (
    "participant_id",
    "code",
    "age",
    "sex",
    "experience",
    "notes",
    "created",
    "n_trials",
)
TRIAL_COLUMNS: tuple[str, ...] = (
    "trial_id",
    "participant_id",
    "participant_code",
    "session_id",
    "session_name",
    "method",
    "order_index",
    "seed",
    "duration_s",
    "status",
    "started_at",
    "ended_at",
    "abort_reason",
    "settings_json",
)
METRICS_COLUMNS: tuple[str, ...] = (
    "trial_id",
    "participant_id",
    "participant_code",
    "session_id",
    "method",
    "order_index",
    "seed",
    "status",
    "started_at",
    "ended_at",
    *METRIC_COLUMNS,
    "stop_replans_per_task",
    "online_replans_per_task",
)
EVENT_COLUMNS: tuple[str, ...] = (
    "event_id",
    "trial_id",
    "participant_code",
    "method",
    "t",
    "kind",
    "payload_json",
)

#: Columns holding ISO 8601 times, per table (``parse_dates`` for pandas).
DATE_COLUMNS: dict[str, tuple[str, ...]] = {
    "participants": ("created",),
    "trials": ("started_at", "ended_at"),
    "metrics": ("started_at", "ended_at"),
    "events": (),
}
_EVENT_BATCH = 5_000


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, datetime):
        return v.isoformat()
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, (dict, list)):
        return json.dumps(v, ensure_ascii=False, sort_keys=True, allow_nan=False)
    return v


def _writer(fp: TextIO, columns: Iterable[str]) -> Any:
    w = csv.writer(fp, lineterminator="\n")
    w.writerow(list(columns))
    return w


def write_participants_csv(repo: StudyRepository, fp: TextIO) -> int:
    """Write every participant (with their number of trials); returns the number of rows."""
    n_trials = select(Trial.participant_id, func.count().label("n")).group_by(Trial.participant_id).subquery()
    q = (
        select(Participant, func.coalesce(n_trials.c.n, 0))
        .outerjoin(n_trials, n_trials.c.participant_id == Participant.id)
        .order_by(Participant.id)
    )
    w = _writer(fp, PARTICIPANT_COLUMNS)
    n = 0
    with repo.session() as s:
        for p, count in s.execute(q):
            w.writerow(
                [_cell(v) for v in (p.id, p.code, p.age, p.sex, p.experience, p.notes, p.created, int(count))]
            )
            n += 1
    return n


def write_trials_csv(repo: StudyRepository, fp: TextIO, *, session_id: int | None = None) -> int:
    """Write every trial (optionally of one study session); returns the number of rows."""
    q = (
        select(Trial, Participant.code, StudySession.name)
        .join(Participant, Participant.id == Trial.participant_id)
        .outerjoin(StudySession, StudySession.id == Trial.session_id)
        .order_by(Trial.id)
    )
    if session_id is not None:
        q = q.where(Trial.session_id == session_id)
    w = _writer(fp, TRIAL_COLUMNS)
    n = 0
    with repo.session() as s:
        for t, code, session_name in s.execute(q):
            values = (
                t.id,
                t.participant_id,
                code,
                t.session_id,
                session_name,
                t.method,
                t.order_index,
                t.seed,
                t.duration_s,
                t.status,
                t.started_at,
                t.ended_at,
                t.abort_reason,
                t.settings or {},
            )
            w.writerow([_cell(v) for v in values])
            n += 1
    return n


def write_metrics_csv(repo: StudyRepository, fp: TextIO, *, session_id: int | None = None) -> int:
    """Write one row per trial that has metrics (any status), joined with participant code and method."""
    w = _writer(fp, METRICS_COLUMNS)
    rows = repo.metrics_rows(session_id=session_id, status=None)
    for row in rows:
        w.writerow([_cell(row[c]) for c in METRICS_COLUMNS])
    return len(rows)


def write_events_csv(
    repo: StudyRepository, fp: TextIO, *, trial_id: int | None = None, session_id: int | None = None
) -> int:
    """Write the events (of one trial, of one session's trials, or all), streamed in batches."""
    q = (
        select(TrialEventRow, Participant.code, Trial.method)
        .join(Trial, Trial.id == TrialEventRow.trial_id)
        .join(Participant, Participant.id == Trial.participant_id)
        .order_by(TrialEventRow.trial_id, TrialEventRow.t, TrialEventRow.id)
        .execution_options(yield_per=_EVENT_BATCH)
    )
    if trial_id is not None:
        q = q.where(TrialEventRow.trial_id == trial_id)
    if session_id is not None:
        q = q.where(Trial.session_id == session_id)
    w = _writer(fp, EVENT_COLUMNS)
    n = 0
    with repo.session() as s:
        for e, code, method in s.execute(q):
            w.writerow([_cell(v) for v in (e.id, e.trial_id, code, method, e.t, e.kind, e.payload or {})])
            n += 1
    return n


def _as_text(write: Callable[..., int], repo: StudyRepository, **kwargs: Any) -> str:
    buf = io.StringIO()
    write(repo, buf, **kwargs)
    return buf.getvalue()


def participants_csv(repo: StudyRepository) -> str:
    """participants.csv as text."""
    return _as_text(write_participants_csv, repo)


def trials_csv(repo: StudyRepository, *, session_id: int | None = None) -> str:
    """trials.csv as text."""
    return _as_text(write_trials_csv, repo, session_id=session_id)


def metrics_csv(repo: StudyRepository, *, session_id: int | None = None) -> str:
    """metrics.csv as text."""
    return _as_text(write_metrics_csv, repo, session_id=session_id)


def events_csv(repo: StudyRepository, *, trial_id: int | None = None, session_id: int | None = None) -> str:
    """events.csv as text."""
    return _as_text(write_events_csv, repo, trial_id=trial_id, session_id=session_id)


#: Table name -> writer, for routes like ``GET /export/{table}.csv``.
CSV_WRITERS: dict[str, Callable[..., int]] = {
    "participants": write_participants_csv,
    "trials": write_trials_csv,
    "metrics": write_metrics_csv,
    "events": write_events_csv,
}


def table_csv(repo: StudyRepository, table: str, **filters: Any) -> str:
    """One table (``participants``, ``trials``, ``metrics``, ``events``) as CSV text.

    Raises:
        KeyError: unknown table name (the message lists the known ones).
    """
    if table not in CSV_WRITERS:
        raise KeyError(f"unknown table {table!r}; choose one of {sorted(CSV_WRITERS)}")
    return _as_text(CSV_WRITERS[table], repo, **filters)


def export_all(repo: StudyRepository, out_dir: Path, *, session_id: int | None = None) -> dict[str, Path]:
    """Write ``participants.csv``, ``trials.csv``, ``metrics.csv``, ``events.csv`` into ``out_dir``
    (trials, metrics and events of one session when ``session_id`` is given). Returns table -> path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    for table, write in CSV_WRITERS.items():
        path = out_dir / f"{table}.csv"
        kwargs = {} if table == "participants" else {"session_id": session_id}
        with path.open("w", encoding="utf-8", newline="") as fp:
            n = write(repo, fp, **kwargs)
        log.info("exported %d %s rows to %s", n, table, path)
        paths[table] = path
    return paths


def export_clips(
    repo: StudyRepository, out_dir: Path, *, session_id: int | None = None, min_frames: int = 40
) -> list[Path]:
    """Write the person's recorded motion of each trial as clips (``.npz``: canonical joints, world frame,
    30 Hz; the format ``hrc hmp train --extra-clips`` and ``hrc hmp calibrate --clips`` read).

    Each tracked body (tracker id) of a trial is its own person; its skeleton is cut where the tracker lost
    it (frames without it); pieces shorter than ``min_frames`` are left out. Files are named
    ``trial<id>_<participant code>_<piece>.npz`` (body id 0) or ``trial<id>_<code>_b<body id>_<piece>.npz``.
    """
    import numpy as np

    from app.prediction.skeleton import JOINTS

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    offset = 0
    while True:
        trials = repo.list_trials(session_id=session_id, offset=offset, limit=200)
        if not trials:
            break
        offset += len(trials)
        for trial in trials:
            frames = repo.load_frames(trial.id)
            if frames is None or frames.skeleton is None:
                continue
            t = np.asarray(frames.t, dtype=np.float64)
            code = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in str(trial.participant_code))
            all_sk = np.asarray(frames.skeleton, dtype=np.float64)  # (T, B, J, 3), :mod:`app.cell.bodies`
            ids = np.asarray(frames.body_ids)
            for body_id in np.unique(ids[ids >= 0]).tolist():  # one person (tracker id) at a time
                slot = ids == body_id  # (T, B): at most one slot per frame
                sk = np.full((len(t), *all_sk.shape[2:]), np.nan)
                rows, slots = np.nonzero(slot)
                sk[rows] = all_sk[rows, slots]
                name = f"trial{trial.id}_{code}" + ("" if body_id == 0 else f"_b{body_id}")
                paths += _export_pieces(sk, t, out_dir / name, min_frames, JOINTS)
    log.info("exported %d clips to %s", len(paths), out_dir)
    return paths


def _export_pieces(sk: Any, t: Any, stem: Path, min_frames: int, joint_names: Any) -> list[Path]:
    """One person's skeleton (T, J, 3) cut into clips ``<stem>_<piece>.npz`` where it was lost (NaN
    frames) or the recording stalled; pieces shorter than ``min_frames`` are left out."""
    import numpy as np

    paths: list[Path] = []
    ok = np.all(np.isfinite(sk), axis=(1, 2))
    # pieces: runs of good frames without a gap of more than 0.1 s
    gap = np.concatenate([[True], np.diff(t) > 0.1])  # a piece starts after a stall...
    cut = ~ok | gap
    starts = np.flatnonzero(ok & (gap | np.concatenate([[True], ~ok[:-1]])))  # ...or a lost person
    for piece, a in enumerate(starts):
        b = a + 1
        while b < len(t) and ok[b] and not cut[b]:
            b += 1
        grid = np.arange(t[a], t[b - 1] + 1e-9, 1.0 / 30.0)  # resampled onto the 30 Hz grid
        if grid.size < min_frames:
            continue
        flat = sk[a:b].reshape(b - a, -1)
        res = np.stack([np.interp(grid, t[a:b], flat[:, k]) for k in range(flat.shape[1])], axis=1)
        path = stem.with_name(f"{stem.name}_{piece}.npz")
        np.savez_compressed(
            path,
            positions=res.reshape(grid.size, -1, 3).astype(np.float32),
            fps=np.float64(30.0),
            joint_names=np.array(joint_names),
        )
        paths.append(path)
    return paths
