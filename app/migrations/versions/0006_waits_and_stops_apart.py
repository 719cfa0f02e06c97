"""The time budget's wait for the person (the goal occupied, or the robot unable to leave where it stands),
counted apart from the wait for a plan, and the stop & replans of a robot under way, counted apart from those
of a robot the speed governor already held still.

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-27
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # trials recorded before this revision counted these waits in budget_waiting_for_plan_s and did not tell
    # the stops apart: NULL (not measured apart), never 0. Plain ADD COLUMN (no batch copy of the table).
    op.add_column("trial_metrics", sa.Column("budget_waiting_for_person_s", sa.Float(), nullable=True))
    op.add_column("trial_metrics", sa.Column("stop_replans_moving", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        batch.drop_column("stop_replans_moving")
        batch.drop_column("budget_waiting_for_person_s")
