"""The proactive method's plan choices per trial: how many executed plans were its forecast's own, the
reactive method's that arrived earlier under the forecast, or the reactive method's where the forecast's
search found none, and the predicted time the reactive ones gained.

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-28
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_INT = ("plans_forecast", "plans_reactive", "plans_reactive_only")


def upgrade() -> None:
    # trials recorded before this revision weighed no candidate: NULL (not counted), never 0
    for name in _INT:
        op.add_column("trial_metrics", sa.Column(name, sa.Integer(), nullable=True))
    op.add_column("trial_metrics", sa.Column("reactive_gain_s", sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        for name in ("reactive_gain_s", *reversed(_INT)):
            batch.drop_column(name)
