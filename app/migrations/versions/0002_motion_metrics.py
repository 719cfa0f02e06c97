"""Trial metrics: time under way and the mean speed scale over it.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-21
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0002"
down_revision: str | None = "0001"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # trials recorded before this revision did not measure them: they read 0
    with op.batch_alter_table("trial_metrics") as batch:
        batch.add_column(sa.Column("time_moving_s", sa.Float(), server_default="0", nullable=False))
        batch.add_column(sa.Column("mean_speed_scale", sa.Float(), server_default="0", nullable=False))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        batch.drop_column("mean_speed_scale")
        batch.drop_column("time_moving_s")
