"""Trained models in every format: a job's policy, a classifier and an HF model also as a
``torch.export`` program (``.pt2``), a job's policy also as ONNX.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None

NEW_COLUMNS = (
    ("jobs", "model_pt2_artifact_id", "SET NULL"),
    ("jobs", "model_onnx_artifact_id", "SET NULL"),
    ("classifiers", "pt2_artifact_id", None),
    ("hf_models", "pt2_artifact_id", None),
)


def upgrade() -> None:
    for table, column, ondelete in NEW_COLUMNS:
        with op.batch_alter_table(table) as batch:
            batch.add_column(sa.Column(column, sa.String(length=32), nullable=True))
            batch.create_foreign_key(
                op.f(f"fk_{table}_{column}_artifacts"),
                "artifacts",
                [column],
                ["id"],
                ondelete=ondelete,
            )


def downgrade() -> None:
    for table, column, _ in reversed(NEW_COLUMNS):
        with op.batch_alter_table(table) as batch:
            batch.drop_constraint(op.f(f"fk_{table}_{column}_artifacts"), type_="foreignkey")
            batch.drop_column(column)
