"""Trial keys: a sweep's deterministic trial identity (unique) and the label of its setting.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-25
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # trials recorded before this revision have no key (NULL: the unique index leaves them alone). Plain
    # ADD COLUMN and CREATE INDEX, not a batch copy: on SQLite a batch drops and re-creates `trials`, and
    # the drop would cascade into the trials' metrics and events
    op.add_column("trials", sa.Column("trial_key", sa.String(400), nullable=True))
    op.add_column("trials", sa.Column("setting_label", sa.String(200), nullable=True))
    op.create_index("ix_trials_trial_key", "trials", ["trial_key"], unique=True)


def downgrade() -> None:
    op.drop_index("ix_trials_trial_key", table_name="trials")
    with op.batch_alter_table("trials") as batch:
        batch.drop_column("setting_label")
        batch.drop_column("trial_key")
