"""Online sessions on the soft label channel: a live run records its channel, and each
decision and label its log-likelihood ratio, so a label re-sent after a crash is the same
soft label (issue 24).

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("live_runs") as batch:
        batch.add_column(sa.Column("label_channel", sa.String(length=8), nullable=True))
    for table in ("live_decisions", "feedback_labels"):
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column("log_likelihood_ratio", sa.Float(), nullable=True))


def downgrade() -> None:
    for table in ("feedback_labels", "live_decisions"):
        with op.batch_alter_table(table) as batch:
            batch.drop_column("log_likelihood_ratio")
    with op.batch_alter_table("live_runs") as batch:
        batch.drop_column("label_channel")
