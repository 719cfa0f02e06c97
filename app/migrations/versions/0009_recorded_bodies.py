"""Every tracked body of a recorded frame: a chunk's skeleton holds (n, B, J, 3) body slots, with the
tracker's id of each (``body_ids`` int32 (n, B), -1 where unused). Chunks recorded before keep NULL here and
their single-body skeleton (n, J, 3).

Revision ID: 0009
Revises: 0008
Create Date: 2026-11-28
"""

from __future__ import annotations

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0009"
down_revision: str | None = "0008"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.add_column("recorded_frames", sa.Column("n_bodies", sa.Integer(), nullable=True))
    op.add_column("recorded_frames", sa.Column("body_ids", sa.LargeBinary(), nullable=True))


def downgrade() -> None:
    # chunks of one body (n_bodies 1) read as before; a chunk of several bodies no longer reads
    with op.batch_alter_table("recorded_frames") as batch:
        batch.drop_column("body_ids")
        batch.drop_column("n_bodies")
