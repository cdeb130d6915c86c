"""Live sessions: runs, markers, epoch decisions, model versions, frames shown (issue 10).

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "live_runs",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("job_id", sa.String(length=32), nullable=True),
        sa.Column("mode", sa.String(length=16), nullable=False),
        sa.Column("options", sa.JSON(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("stop_requested", sa.Boolean(), nullable=False),
        sa.Column("sim_session_id", sa.String(length=200), nullable=True),
        sa.Column("hf_session_id", sa.String(length=64), nullable=True),
        sa.Column("eeg_classifier_id", sa.String(length=64), nullable=True),
        sa.Column("recording_id", sa.Integer(), nullable=True),
        sa.Column("hf_model_id", sa.Integer(), nullable=True),
        sa.Column("follow_up_job_id", sa.String(length=32), nullable=True),
        sa.Column("resumes", sa.Integer(), nullable=False),
        sa.Column("result", sa.JSON(), nullable=True),
        sa.Column("error", sa.Text(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.CheckConstraint(
            "mode IN ('calibration', 'test', 'online')", name=op.f("ck_live_runs_mode_allowed")
        ),
        sa.CheckConstraint(
            "status IN ('queued', 'running', 'completed', 'stopped', 'failed')",
            name=op.f("ck_live_runs_status_allowed"),
        ),
        sa.ForeignKeyConstraint(
            ["follow_up_job_id"],
            ["jobs.id"],
            name=op.f("fk_live_runs_follow_up_job_id_jobs"),
            ondelete="SET NULL",
        ),
        sa.ForeignKeyConstraint(
            ["hf_model_id"],
            ["hf_models.id"],
            name=op.f("fk_live_runs_hf_model_id_hf_models"),
            ondelete="SET NULL",
        ),
        sa.ForeignKeyConstraint(
            ["job_id"], ["jobs.id"], name=op.f("fk_live_runs_job_id_jobs"), ondelete="SET NULL"
        ),
        sa.ForeignKeyConstraint(
            ["recording_id"],
            ["recordings.id"],
            name=op.f("fk_live_runs_recording_id_recordings"),
            ondelete="SET NULL",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_live_runs_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_runs")),
    )
    op.create_index(op.f("ix_live_runs_session_id"), "live_runs", ["session_id"], unique=False)
    op.create_table(
        "live_decisions",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("reason", sa.Text(), nullable=True),
        sa.Column("feedback", sa.String(length=16), nullable=True),
        sa.Column("p_error", sa.Float(), nullable=True),
        sa.Column("oracle_correct", sa.Boolean(), nullable=True),
        sa.Column("classifier_id", sa.String(length=64), nullable=True),
        sa.Column("epoch_end_ts", sa.Float(), nullable=True),
        sa.Column("decided_ts", sa.Float(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.CheckConstraint(
            "status IN ('ok', 'rejected')", name=op.f("ck_live_decisions_status_allowed")
        ),
        sa.ForeignKeyConstraint(
            ["run_id"],
            ["live_runs.id"],
            name=op.f("fk_live_decisions_run_id_live_runs"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_live_decisions_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_decisions")),
        sa.UniqueConstraint("run_id", "step", name="uq_live_decisions_step"),
    )
    op.create_index(
        op.f("ix_live_decisions_session_id"), "live_decisions", ["session_id"], unique=False
    )
    op.create_table(
        "live_frames_shown",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("shown_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("received_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["run_id"],
            ["live_runs.id"],
            name=op.f("fk_live_frames_shown_run_id_live_runs"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_live_frames_shown_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_frames_shown")),
        sa.UniqueConstraint("run_id", "step", name="uq_live_frames_shown_step"),
    )
    op.create_index(
        op.f("ix_live_frames_shown_session_id"), "live_frames_shown", ["session_id"], unique=False
    )
    op.create_table(
        "live_markers",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("sim_session_id", sa.String(length=200), nullable=False),
        sa.Column("sim_step", sa.Integer(), nullable=False),
        sa.Column("episode", sa.Integer(), nullable=False),
        sa.Column("action", sa.Integer(), nullable=False),
        sa.Column("oracle_correct", sa.Boolean(), nullable=True),
        sa.Column("observation", sa.JSON(), nullable=False),
        sa.Column("policy_version", sa.Integer(), nullable=True),
        sa.Column("marker_ts", sa.Float(), nullable=False),
        sa.Column("eeg_ts", sa.Float(), nullable=False),
        sa.Column("executed_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["run_id"],
            ["live_runs.id"],
            name=op.f("fk_live_markers_run_id_live_runs"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_live_markers_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_markers")),
        sa.UniqueConstraint("run_id", "step", name="uq_live_markers_step"),
    )
    op.create_index(
        op.f("ix_live_markers_session_id"), "live_markers", ["session_id"], unique=False
    )
    op.create_table(
        "live_model_versions",
        sa.Column("id", sa.BigInteger().with_variant(sa.Integer(), "sqlite"), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("session_id", sa.Integer(), nullable=False),
        sa.Column("step", sa.Integer(), nullable=False),
        sa.Column("labels", sa.Integer(), nullable=False),
        sa.Column("model_version", sa.Integer(), nullable=False),
        sa.Column("metrics", sa.JSON(), nullable=False),
        sa.Column("updated_ts", sa.Float(), nullable=False),
        sa.Column("next_ready_ts", sa.Float(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(
            ["run_id"],
            ["live_runs.id"],
            name=op.f("fk_live_model_versions_run_id_live_runs"),
            ondelete="CASCADE",
        ),
        sa.ForeignKeyConstraint(
            ["session_id"],
            ["sessions.id"],
            name=op.f("fk_live_model_versions_session_id_sessions"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_live_model_versions")),
        sa.UniqueConstraint("run_id", "step", name="uq_live_model_versions_step"),
    )
    op.create_index(
        op.f("ix_live_model_versions_session_id"),
        "live_model_versions",
        ["session_id"],
        unique=False,
    )


def downgrade() -> None:
    op.drop_index(op.f("ix_live_model_versions_session_id"), table_name="live_model_versions")
    op.drop_table("live_model_versions")
    op.drop_index(op.f("ix_live_markers_session_id"), table_name="live_markers")
    op.drop_table("live_markers")
    op.drop_index(op.f("ix_live_frames_shown_session_id"), table_name="live_frames_shown")
    op.drop_table("live_frames_shown")
    op.drop_index(op.f("ix_live_decisions_session_id"), table_name="live_decisions")
    op.drop_table("live_decisions")
    op.drop_index(op.f("ix_live_runs_session_id"), table_name="live_runs")
    op.drop_table("live_runs")
