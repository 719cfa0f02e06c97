"""SQLAlchemy 2 models of the study records: participants, study sessions, trials, metrics, events, frames.

Every time column stores an aware UTC datetime (:class:`UTCDateTime`); trial-relative times (event ``t``,
frame times) are seconds since the trial started on the runtime's clock (simulated in headless runs).
The schema is created by the Alembic migrations in ``migrations/`` (see :func:`app.study.db.upgrade_to_head`),
never by ``create_all`` in the application.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    CheckConstraint,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Text,
    UniqueConstraint,
)
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship
from sqlalchemy.types import TypeDecorator

#: Constraint names are deterministic so that migrations can refer to them on every backend.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

TRIAL_STATUSES: tuple[str, ...] = ("running", "completed", "aborted")


def utcnow() -> datetime:
    """The current time as an aware UTC datetime."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """A ``TIMESTAMP WITH TIME ZONE`` that only accepts aware datetimes and always returns aware UTC ones.

    SQLite has no time zones and returns naive values: they were stored as UTC, so UTC is attached back.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value!r}: pass an aware datetime (e.g. datetime.now(UTC))")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base of the study tables."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Participant(Base):
    """A person (or a simulated operator) who takes part in trials. ``code`` is the pseudonymous id."""

    __tablename__ = "participants"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    code: Mapped[str] = mapped_column(String(64), unique=True)
    age: Mapped[int | None] = mapped_column(Integer)
    sex: Mapped[str | None] = mapped_column(String(32))
    experience: Mapped[str | None] = mapped_column(String(200))
    notes: Mapped[str] = mapped_column(Text, default="")
    created: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)

    trials: Mapped[list[Trial]] = relationship(back_populates="participant", passive_deletes=True)

    __table_args__ = (CheckConstraint("age IS NULL OR (age >= 0 AND age < 150)", name="age_range"),)


class StudySession(Base):
    """A study session (a day in the lab, or one headless study run) that groups trials."""

    __tablename__ = "study_sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    notes: Mapped[str] = mapped_column(Text, default="")
    created: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)

    trials: Mapped[list[Trial]] = relationship(back_populates="session", passive_deletes=True)


class Trial(Base):
    """One trial: a participant works beside the robot driven by one method for a set duration.

    ``settings`` is a JSON snapshot of the application settings the trial ran with (secrets removed).
    ``order_index`` is the position of the trial in the participant's sequence within its session (0, 1, ...).
    ``trial_key`` (unique, None outside sweeps) is a sweep trial's deterministic identity (sweep, setting
    label, participant, method, seed): a completed sweep trial is stored once, whoever stores it;
    ``setting_label`` names the sweep's setting the trial ran with.
    """

    __tablename__ = "trials"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    participant_id: Mapped[int] = mapped_column(ForeignKey("participants.id", ondelete="CASCADE"), index=True)
    session_id: Mapped[int | None] = mapped_column(
        ForeignKey("study_sessions.id", ondelete="SET NULL"), index=True
    )
    method: Mapped[str] = mapped_column(String(16))
    order_index: Mapped[int] = mapped_column(Integer, default=0)
    seed: Mapped[int] = mapped_column(BigInteger, default=0)
    duration_s: Mapped[float | None] = mapped_column(Float)
    settings: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    ended_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    status: Mapped[str] = mapped_column(String(16), default="running", index=True)
    abort_reason: Mapped[str | None] = mapped_column(Text)
    trial_key: Mapped[str | None] = mapped_column(String(400), unique=True, index=True)
    setting_label: Mapped[str | None] = mapped_column(String(200))

    participant: Mapped[Participant] = relationship(back_populates="trials")
    session: Mapped[StudySession | None] = relationship(back_populates="trials")
    metrics: Mapped[TrialMetricsRow | None] = relationship(
        back_populates="trial", uselist=False, passive_deletes=True
    )

    __table_args__ = (
        CheckConstraint("method IN ('proactive', 'reactive')", name="method"),
        CheckConstraint("status IN ('running', 'completed', 'aborted')", name="status"),
        CheckConstraint("order_index >= 0", name="order_index"),
    )


class TrialMetricsRow(Base):
    """The metrics of one trial: one column per stored field of :class:`app.control.metrics.TrialMetrics`
    (``method`` lives on the trial). A non-finite ``min_separation_m`` or ``min_separation_moving_m`` (no
    person seen, or the robot never moved) is stored as NULL."""

    __tablename__ = "trial_metrics"

    trial_id: Mapped[int] = mapped_column(ForeignKey("trials.id", ondelete="CASCADE"), primary_key=True)
    duration_s: Mapped[float] = mapped_column(Float)
    completed_tasks: Mapped[int] = mapped_column(Integer)
    plans_computed: Mapped[int] = mapped_column(Integer)
    avg_planning_time_s: Mapped[float] = mapped_column(Float)
    p95_planning_time_s: Mapped[float] = mapped_column(Float)
    stop_replans: Mapped[int] = mapped_column(Integer)
    # revision 0006; NULL: a trial stored before it (not counted apart)
    stop_replans_moving: Mapped[int | None] = mapped_column(Integer)
    online_replans: Mapped[int] = mapped_column(Integer)
    deadline_misses: Mapped[int] = mapped_column(Integer)
    emergency_plans: Mapped[int] = mapped_column(Integer)
    plan_failures: Mapped[int] = mapped_column(Integer)
    min_separation_m: Mapped[float | None] = mapped_column(Float)
    violations: Mapped[int] = mapped_column(Integer)
    contacts: Mapped[int] = mapped_column(Integer, server_default="0")
    violation_time_s: Mapped[float] = mapped_column(Float, server_default="0")
    violations_iso: Mapped[int] = mapped_column(Integer, server_default="0")
    # revision 0007, the judge of ISO 13855's person with PFL; NULL: a trial judged before it
    violations_person_faster: Mapped[int | None] = mapped_column(Integer)
    harmful_contacts: Mapped[int | None] = mapped_column(Integer)
    violations_measured_vh: Mapped[int | None] = mapped_column(Integer)
    exceedance_s: Mapped[float | None] = mapped_column(Float)
    max_approach_mps: Mapped[float | None] = mapped_column(Float)
    intrusions: Mapped[int] = mapped_column(Integer, server_default="0")
    min_separation_moving_m: Mapped[float | None] = mapped_column(Float)
    time_stopped_s: Mapped[float] = mapped_column(Float)
    time_nominal_s: Mapped[float] = mapped_column(Float)
    time_collision_avoidance_s: Mapped[float] = mapped_column(Float)
    time_moving_s: Mapped[float] = mapped_column(Float, server_default="0")
    mean_speed_scale: Mapped[float] = mapped_column(Float, server_default="0")
    # the time budget and the arrivals (revision 0005; NULL: a trial stored before it, not measured)
    budget_moving_full_s: Mapped[float | None] = mapped_column(Float)
    budget_moving_scaled_s: Mapped[float | None] = mapped_column(Float)
    budget_braking_s: Mapped[float | None] = mapped_column(Float)
    budget_stopped_s: Mapped[float | None] = mapped_column(Float)
    budget_planned_wait_s: Mapped[float | None] = mapped_column(Float)
    budget_gripper_s: Mapped[float | None] = mapped_column(Float)
    # revision 0006; NULL: a trial stored before it (its waits for the person count as waits for a plan)
    budget_waiting_for_person_s: Mapped[float | None] = mapped_column(Float)
    budget_waiting_for_plan_s: Mapped[float | None] = mapped_column(Float)
    budget_idle_s: Mapped[float | None] = mapped_column(Float)
    arrivals: Mapped[int | None] = mapped_column(Integer)
    arrival_error_median_abs_s: Mapped[float | None] = mapped_column(Float)
    arrival_error_bias_s: Mapped[float | None] = mapped_column(Float)
    median_plan_s: Mapped[float | None] = mapped_column(Float)
    # revision 0008, the reactive method's plan as a candidate; NULL: a trial recorded before it
    plans_forecast: Mapped[int | None] = mapped_column(Integer)
    plans_reactive: Mapped[int | None] = mapped_column(Integer)
    plans_reactive_only: Mapped[int | None] = mapped_column(Integer)
    reactive_gain_s: Mapped[float | None] = mapped_column(Float)
    stale_stops: Mapped[int] = mapped_column(Integer)
    frames_received: Mapped[int] = mapped_column(Integer)
    frames_rejected: Mapped[int] = mapped_column(Integer)

    trial: Mapped[Trial] = relationship(back_populates="metrics")


#: The TrialMetrics fields stored as columns of :class:`TrialMetricsRow` (every field but ``method``).
METRIC_COLUMNS: tuple[str, ...] = (
    "duration_s",
    "completed_tasks",
    "plans_computed",
    "avg_planning_time_s",
    "p95_planning_time_s",
    "stop_replans",
    "stop_replans_moving",
    "online_replans",
    "deadline_misses",
    "emergency_plans",
    "plan_failures",
    "min_separation_m",
    "violations",
    "contacts",
    "violation_time_s",
    "violations_iso",
    "violations_person_faster",
    "harmful_contacts",
    "violations_measured_vh",
    "exceedance_s",
    "max_approach_mps",
    "intrusions",
    "min_separation_moving_m",
    "time_stopped_s",
    "time_nominal_s",
    "time_collision_avoidance_s",
    "time_moving_s",
    "mean_speed_scale",
    "budget_moving_full_s",
    "budget_moving_scaled_s",
    "budget_braking_s",
    "budget_stopped_s",
    "budget_planned_wait_s",
    "budget_gripper_s",
    "budget_waiting_for_person_s",
    "budget_waiting_for_plan_s",
    "budget_idle_s",
    "arrivals",
    "arrival_error_median_abs_s",
    "arrival_error_bias_s",
    "median_plan_s",
    "plans_forecast",
    "plans_reactive",
    "plans_reactive_only",
    "reactive_gain_s",
    "stale_stops",
    "frames_received",
    "frames_rejected",
)


class TrialEventRow(Base):
    """One timestamped event of a trial (``t``: seconds since the trial started; ``kind``: an EVENT_KINDS)."""

    __tablename__ = "trial_events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    trial_id: Mapped[int] = mapped_column(ForeignKey("trials.id", ondelete="CASCADE"))
    t: Mapped[float] = mapped_column(Float)
    kind: Mapped[str] = mapped_column(String(32))
    payload: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)

    __table_args__ = (Index("ix_trial_events_trial_id_t", "trial_id", "t"),)


class RecordedFrame(Base):
    """A chunk of recorded frames of a trial, for replay: ``n_frames`` consecutive frames stored compactly.

    Columns hold little-endian raw arrays: ``t`` float64 (n,) seconds since the trial started; ``q``
    float32 (n, 6) robot joint positions (rad); ``skeleton`` float32 (n, B, J, 3) every tracked body's joint
    positions in the world frame (m), NaN in the body slots a frame does not use, or NULL when the chunk has
    no skeleton at all; ``body_ids`` int32 (n, B) the tracker's id of each slot, -1 where unused
    (:mod:`app.cell.bodies`). Chunks written before revision 0009 have ``n_bodies`` and ``body_ids`` NULL and
    ``skeleton`` (n, J, 3), one body (NaN rows where nobody was seen).
    """

    __tablename__ = "recorded_frames"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    trial_id: Mapped[int] = mapped_column(ForeignKey("trials.id", ondelete="CASCADE"))
    chunk_index: Mapped[int] = mapped_column(Integer)
    n_frames: Mapped[int] = mapped_column(Integer)
    n_joints: Mapped[int] = mapped_column(Integer)
    t: Mapped[bytes] = mapped_column(LargeBinary)
    q: Mapped[bytes] = mapped_column(LargeBinary)
    skeleton: Mapped[bytes | None] = mapped_column(LargeBinary)
    n_bodies: Mapped[int | None] = mapped_column(Integer, nullable=True)
    body_ids: Mapped[bytes | None] = mapped_column(LargeBinary, nullable=True)

    __table_args__ = (
        UniqueConstraint("trial_id", "chunk_index", name="uq_recorded_frames_trial_chunk"),
        CheckConstraint("n_frames > 0", name="n_frames"),
    )
