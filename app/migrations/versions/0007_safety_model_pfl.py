"""The safety model of ISO 13855's person with power and force limiting: its judge's counts per trial
(violations opened by a person faster than assumed, harmful contacts, the exceedance and the fastest approach,
and the measured-speed stress figure of earlier versions).

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-27
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_INT = ("violations_person_faster", "harmful_contacts", "violations_measured_vh")
_FLOAT = ("exceedance_s", "max_approach_mps")


def upgrade() -> None:
    # trials judged before this revision had another judge (the measured speed, no PFL): NULL, never 0
    for name in _INT:
        op.add_column("trial_metrics", sa.Column(name, sa.Integer(), nullable=True))
    for name in _FLOAT:
        op.add_column("trial_metrics", sa.Column(name, sa.Float(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("trial_metrics") as batch:
        for name in (*_FLOAT, *_INT):
            batch.drop_column(name)
