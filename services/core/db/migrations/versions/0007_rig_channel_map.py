"""Rigs carry their amplifier's channel map (device name -> standard 10-20/10-10 name).

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("rigs") as batch:
        batch.add_column(sa.Column("channel_map", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("rigs") as batch:
        batch.drop_column("channel_map")
