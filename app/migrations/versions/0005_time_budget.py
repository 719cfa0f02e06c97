"""Trial metrics of the time budget (where a trial's time went, per part) and of the plans' arrivals (how many
reached their goal, the predicted against the executed arrival, the median planned duration).

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-26
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

#: The time budget's parts (app.control.counters.TIME_BUDGET as of this revision: a migration does not
#: follow later changes of the code).
_BUDGET = (
    "moving_full",
    "moving_scaled",
    "braking",
    "stopped",
    "planned_wait",
    "gripper",
    "waiting_for_plan",
    "idle",
)
_ARRIVALS = ("arrival_error_median_abs_s", "arrival_error_bias_s", "median_plan_s")


def upgrade() -> None:
    # trials recorded before this revision did not keep a time budget: their columns stay NULL (unknown),
    # never 0. Plain ADD COLUMN (no batch copy of the table).
    for part in _BUDGET:
        op.add_column("trial_metrics", sa.Column(f"budget_{part}_s", sa.Float(), nullable=True))
    op.add_column("trial_metrics", sa.Column("arrivals", sa.Integer(), nullable=True))
    for name in _ARRIVALS:
        op.add_column("trial_metrics", sa.Column(name, sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        for name in (*reversed(_ARRIVALS), "arrivals", *(f"budget_{p}_s" for p in reversed(_BUDGET))):
            batch.drop_column(name)
