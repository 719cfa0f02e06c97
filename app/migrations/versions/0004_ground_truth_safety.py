"""Trial metrics of the ground-truth safety monitor: contacts, time in violation, violations judged with
ISO 13855's constant human speeds, intrusions, and the smallest separation while the robot moved.

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-25
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # trials recorded before this revision were judged by the earlier monitor: the new counts read 0 and the
    # moving separation NULL (not measured). Plain ADD COLUMN (no batch copy of the table).
    op.add_column("trial_metrics", sa.Column("contacts", sa.Integer(), server_default="0", nullable=False))
    op.add_column(
        "trial_metrics", sa.Column("violation_time_s", sa.Float(), server_default="0", nullable=False)
    )
    op.add_column(
        "trial_metrics", sa.Column("violations_iso", sa.Integer(), server_default="0", nullable=False)
    )
    op.add_column("trial_metrics", sa.Column("intrusions", sa.Integer(), server_default="0", nullable=False))
    op.add_column("trial_metrics", sa.Column("min_separation_moving_m", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        for name in ("min_separation_moving_m", "intrusions", "violations_iso", "violation_time_s", "contacts"):
            batch.drop_column(name)
