"""``reproduce_run``: one run of a reproduction, created by its ``reproduce`` job (the
config is the learner's run spec)."""

from __future__ import annotations

from services.platform.jobs.guided_ppo import run_summary
from services.platform.jobs.kind import JobKind

KIND = JobKind(
    name="reproduce_run",
    title="Run of a reproduction",
    config=None,
    summary=run_summary,
    counts_steps=True,
)
