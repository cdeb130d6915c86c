"""Lab resources: rigs, subjects, sessions, recordings, classifiers, HF models, feedback labels.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

BigIntId = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def _when(name: str, nullable: bool = False) -> sa.Column:
    return sa.Column(name, sa.DateTime(timezone=True), nullable=nullable)


def _fk(table: str, column: str, target: str, ondelete: str | None) -> sa.ForeignKeyConstraint:
    return sa.ForeignKeyConstraint(
        [column],
        [f"{target}.id"],
        name=op.f(f"fk_{table}_{column}_{target}"),
        ondelete=ondelete,
    )


def upgrade() -> None:
    op.create_table(
        "rigs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=100), nullable=False),
        sa.Column("location", sa.String(length=200), nullable=False),
        sa.Column("description", sa.Text(), nullable=False),
        sa.Column("active", sa.Boolean(), nullable=False),
        _when("created_at"),
        _when("updated_at"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_rigs")),
        sa.UniqueConstraint("name", name=op.f("uq_rigs_name")),
    )
    op.create_table(
        "subjects",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("code", sa.String(length=64), nullable=False),
        sa.Column("notes", sa.Text(), nullable=False),
        _when("created_at"),
        _when("updated_at"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_subjects")),
        sa.UniqueConstraint("code", name=op.f("uq_subjects_code")),
    )
    op.create_table(
        "sessions",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("subject_id", sa.Integer(), nullable=False),
        sa.Column("rig_id", sa.Integer(), nullable=True),
        sa.Column("kind", sa.String(length=16), nullable=False),
        _when("scheduled_at"),
        sa.Column("duration_minutes", sa.Integer(), nullable=False),
        _when("ends_at"),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("operator_id", sa.Integer(), nullable=True),
        sa.Column("notes", sa.Text(), nullable=False),
        _when("created_at"),
        _when("updated_at"),
        sa.CheckConstraint(
            "kind IN ('calibration', 'test', 'online', 'rl')",
            name=op.f("ck_sessions_kind_allowed"),
        ),
        sa.CheckConstraint(
            "status IN ('scheduled', 'running', 'completed', 'cancelled', 'failed')",
            name=op.f("ck_sessions_status_allowed"),
        ),
        sa.CheckConstraint("duration_minutes > 0", name=op.f("ck_sessions_duration_positive")),
        _fk("sessions", "operator_id", "users", "SET NULL"),
        _fk("sessions", "rig_id", "rigs", "RESTRICT"),
        _fk("sessions", "subject_id", "subjects", "CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_sessions")),
    )
    op.create_index("ix_sessions_rig_id_scheduled_at", "sessions", ["rig_id", "scheduled_at"])
    op.create_index(op.f("ix_sessions_scheduled_at"), "sessions", ["scheduled_at"])
    op.create_index(op.f("ix_sessions_status"), "sessions", ["status"])
    op.create_index(
        "ix_sessions_subject_id_scheduled_at", "sessions", ["subject_id", "scheduled_at"]
    )
    op.create_table(
        "recordings",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("artifact_id", sa.String(length=32), nullable=False),
        sa.Column("filename", sa.String(length=255), nullable=False),
        sa.Column("sha256", sa.String(length=64), nullable=False),
        sa.Column("size_bytes", sa.BigInteger(), nullable=False),
        sa.Column("synthetic", sa.Boolean(), nullable=True),
        sa.Column("n_channels", sa.Integer(), nullable=True),
        sa.Column("channels", sa.JSON(), nullable=True),
        sa.Column("sfreq", sa.Float(), nullable=True),
        sa.Column("duration_s", sa.Float(), nullable=True),
        sa.Column("validation_status", sa.String(length=16), nullable=False),
        sa.Column("validation_reason", sa.Text(), nullable=True),
        _when("validated_at", nullable=True),
        sa.Column("uploaded_by_id", sa.Integer(), nullable=True),
        _when("created_at"),
        sa.CheckConstraint(
            "validation_status IN ('pending', 'valid', 'invalid')",
            name=op.f("ck_recordings_validation_status_allowed"),
        ),
        _fk("recordings", "artifact_id", "artifacts", None),
        _fk("recordings", "session_id", "sessions", "CASCADE"),
        _fk("recordings", "uploaded_by_id", "users", "SET NULL"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_recordings")),
    )
    op.create_index(op.f("ix_recordings_session_id"), "recordings", ["session_id"])
    op.create_table(
        "classifiers",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("subject_id", sa.Integer(), nullable=True),
        sa.Column("recording_id", sa.Integer(), nullable=True),
        sa.Column("job_id", sa.String(length=32), nullable=True),
        sa.Column("onnx_artifact_id", sa.String(length=32), nullable=True),
        sa.Column("torchscript_artifact_id", sa.String(length=32), nullable=True),
        sa.Column("metrics", sa.JSON(), nullable=False),
        _when("created_at"),
        _fk("classifiers", "job_id", "jobs", "SET NULL"),
        _fk("classifiers", "onnx_artifact_id", "artifacts", None),
        _fk("classifiers", "recording_id", "recordings", "SET NULL"),
        _fk("classifiers", "subject_id", "subjects", "CASCADE"),
        _fk("classifiers", "torchscript_artifact_id", "artifacts", None),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_classifiers")),
    )
    op.create_index(op.f("ix_classifiers_subject_id"), "classifiers", ["subject_id"])
    op.create_table(
        "hf_models",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("task", sa.String(length=8), nullable=False),
        sa.Column("feedback_accuracy", sa.Float(), nullable=True),
        sa.Column("n_labels", sa.Integer(), nullable=True),
        sa.Column("session_id", sa.Integer(), nullable=True),
        sa.Column("job_id", sa.String(length=32), nullable=True),
        sa.Column("torchscript_artifact_id", sa.String(length=32), nullable=True),
        sa.Column("onnx_artifact_id", sa.String(length=32), nullable=True),
        sa.Column("metrics", sa.JSON(), nullable=False),
        _when("created_at"),
        _fk("hf_models", "job_id", "jobs", "SET NULL"),
        _fk("hf_models", "onnx_artifact_id", "artifacts", None),
        _fk("hf_models", "session_id", "sessions", "SET NULL"),
        _fk("hf_models", "torchscript_artifact_id", "artifacts", None),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_hf_models")),
    )
    op.create_table(
        "feedback_labels",
        sa.Column("id", BigIntId, nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("state", sa.JSON(), nullable=False),
        sa.Column("action", sa.Integer(), nullable=False),
        sa.Column("decoded_error", sa.Boolean(), nullable=True),
        sa.Column("p_error", sa.Float(), nullable=True),
        sa.Column("oracle_error", sa.Boolean(), nullable=True),
        _when("shown_at", nullable=True),
        _when("decoded_at", nullable=True),
        _when("created_at"),
        _fk("feedback_labels", "session_id", "sessions", "CASCADE"),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_feedback_labels")),
        sa.UniqueConstraint("session_id", "step", name="uq_feedback_labels_step"),
    )


def downgrade() -> None:
    for table in (
        "feedback_labels",
        "hf_models",
        "classifiers",
        "recordings",
        "sessions",
        "subjects",
        "rigs",
    ):
        op.drop_table(table)
