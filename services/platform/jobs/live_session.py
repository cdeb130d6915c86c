"""``live_session``: a lab session's calibration, test or online loop, started from the
session (``POST /api/v1/sessions/{id}/start``), not submitted."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from services.platform.jobs.kind import JobKind


def summary(config: Mapping[str, Any]) -> str:
    """``session 4: online run, accelerated, 300 actions``."""
    how = "paced" if config.get("accelerated") is False else "accelerated"
    text = f"session {config.get('session_id')}: {config.get('mode') or 'live'} run, {how}"
    return f"{text}, {config['n_actions']} actions" if config.get("n_actions") else text


KIND = JobKind(name="live_session", title="Live session", config=None, summary=summary)
