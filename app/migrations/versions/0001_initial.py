"""Initial study schema: participants, study sessions, trials, trial metrics, trial events, recorded frames.

Revision ID: 0001
Revises:
Create Date: 2026-11-21
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "participants",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("code", sa.String(length=64), nullable=False),
        sa.Column("age", sa.Integer(), nullable=True),
        sa.Column("sex", sa.String(length=32), nullable=True),
        sa.Column("experience", sa.String(length=200), nullable=True),
        sa.Column("notes", sa.Text(), nullable=False),
        sa.Column("created", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint("age IS NULL OR (age >= 0 AND age < 150)", name=op.f("ck_participants_age_range")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_participants")),
        sa.UniqueConstraint("code", name=op.f("uq_participants_code")),
    )
    op.create_table(
        "study_sessions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("notes", sa.Text(), nullable=False),
        sa.Column("created", sa.DateTime(timezone=True), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_study_sessions")),
    )
    op.create_table(
        "trials",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("participant_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=True),
        sa.Column("method", sa.String(length=16), nullable=False),
        sa.Column("order_index", sa.Integer(), nullable=False),
        sa.Column("seed", sa.BigInteger(), nullable=False),
        sa.Column("duration_s", sa.Float(), nullable=True),
        sa.Column("settings", sa.JSON(), nullable=False),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("ended_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("abort_reason", sa.Text(), nullable=True),
        sa.CheckConstraint("method IN ('proactive', 'reactive')", name=op.f("ck_trials_method")),
        sa.CheckConstraint("status IN ('running', 'completed', 'aborted')", name=op.f("ck_trials_status")),
        sa.CheckConstraint("order_index >= 0", name=op.f("ck_trials_order_index")),
        sa.ForeignKeyConstraint(
            ["participant_id"],
            ["participants.id"],
            name=op.f("fk_trials_participant_id_participants"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["study_sessions.id"],
            name=op.f("fk_trials_session_id_study_sessions"),
            ondelete="SET NULL",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_trials")),
    )
    op.create_index(op.f("ix_trials_participant_id"), "trials", ["participant_id"], unique=False)
    op.create_index(op.f("ix_trials_session_id"), "trials", ["session_id"], unique=False)
    op.create_index(op.f("ix_trials_status"), "trials", ["status"], unique=False)
    op.create_table(
        "trial_metrics",
        sa.Column("trial_id", sa.Integer(), nullable=False),
        sa.Column("duration_s", sa.Float(), nullable=False),
        sa.Column("completed_tasks", sa.Integer(), nullable=False),
        sa.Column("plans_computed", sa.Integer(), nullable=False),
        sa.Column("avg_planning_time_s", sa.Float(), nullable=False),
        sa.Column("p95_planning_time_s", sa.Float(), nullable=False),
        sa.Column("stop_replans", sa.Integer(), nullable=False),
        sa.Column("online_replans", sa.Integer(), nullable=False),
        sa.Column("deadline_misses", sa.Integer(), nullable=False),
        sa.Column("emergency_plans", sa.Integer(), nullable=False),
        sa.Column("plan_failures", sa.Integer(), nullable=False),
        sa.Column("min_separation_m", sa.Float(), nullable=True),
        sa.Column("violations", sa.Integer(), nullable=False),
        sa.Column("time_stopped_s", sa.Float(), nullable=False),
        sa.Column("time_nominal_s", sa.Float(), nullable=False),
        sa.Column("time_collision_avoidance_s", sa.Float(), nullable=False),
        sa.Column("stale_stops", sa.Integer(), nullable=False),
        sa.Column("frames_received", sa.Integer(), nullable=False),
        sa.Column("frames_rejected", sa.Integer(), nullable=False),
        sa.ForeignKeyConstraint(
            ["trial_id"], ["trials.id"], name=op.f("fk_trial_metrics_trial_id_trials"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("trial_id", name=op.f("pk_trial_metrics")),
    )
    op.create_table(
        "trial_events",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("trial_id", sa.Integer(), nullable=False),
        sa.Column("t", sa.Float(), nullable=False),
        sa.Column("kind", sa.String(length=32), nullable=False),
        sa.Column("payload", sa.JSON(), nullable=False),
        sa.ForeignKeyConstraint(
            ["trial_id"], ["trials.id"], name=op.f("fk_trial_events_trial_id_trials"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_trial_events")),
    )
    op.create_index("ix_trial_events_trial_id_t", "trial_events", ["trial_id", "t"], unique=False)
    op.create_table(
        "recorded_frames",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("trial_id", sa.Integer(), nullable=False),
        sa.Column("chunk_index", sa.Integer(), nullable=False),
        sa.Column("n_frames", sa.Integer(), nullable=False),
        sa.Column("n_joints", sa.Integer(), nullable=False),
        sa.Column("t", sa.LargeBinary(), nullable=False),
        sa.Column("q", sa.LargeBinary(), nullable=False),
        sa.Column("skeleton", sa.LargeBinary(), nullable=True),
        sa.CheckConstraint("n_frames > 0", name=op.f("ck_recorded_frames_n_frames")),
        sa.ForeignKeyConstraint(
            ["trial_id"], ["trials.id"], name=op.f("fk_recorded_frames_trial_id_trials"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_recorded_frames")),
        sa.UniqueConstraint("trial_id", "chunk_index", name="uq_recorded_frames_trial_chunk"),
    )


def downgrade() -> None:
    op.drop_table("recorded_frames")
    op.drop_index("ix_trial_events_trial_id_t", table_name="trial_events")
    op.drop_table("trial_events")
    op.drop_table("trial_metrics")
    op.drop_index(op.f("ix_trials_status"), table_name="trials")
    op.drop_index(op.f("ix_trials_session_id"), table_name="trials")
    op.drop_index(op.f("ix_trials_participant_id"), table_name="trials")
    op.drop_table("trials")
    op.drop_table("study_sessions")
    op.drop_table("participants")
