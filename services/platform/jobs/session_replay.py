"""``session_replay``: an online session replayed through the live decoder and the learner
(a new pi_HF)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import Field

from services.core.schemas import MAX_ROW_ID
from services.platform.jobs.kind import JobConfig, JobKind, form_hints


class SessionReplayConfig(JobConfig):
    """Replay an online session through the live decoder and the learner (a new pi_HF)."""

    session_id: int = Field(
        ge=1,
        le=MAX_ROW_ID,
        title="Session",
        description="The id of an online session that has run (its page links the replay).",
    )
    classifier_id: int | None = Field(
        None,
        ge=1,
        le=MAX_ROW_ID,
        title="Classifier",
        description="Decode with this classifier (default: the session's).",
        json_schema_extra=form_hints(references="classifiers"),
    )
    label_budget: int | None = Field(
        None,
        ge=1,
        le=100_000,
        title="Label budget",
        description="Labels of the new pi_HF (default: the session's).",
    )


def summary(config: Mapping[str, Any]) -> str:
    """``replay of session 7``."""
    return f"replay of session {config.get('session_id')}"


KIND = JobKind(
    name="session_replay", title="Session replay", config=SessionReplayConfig, summary=summary
)
