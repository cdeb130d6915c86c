"""``reproduce_batch``: runs of a reproduction trained together in lockstep in one worker,
created by its ``reproduce`` job (the config: ``runs``, the learner's run specs, and
``checkpoint_every``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from services.platform.jobs.guided_ppo import run_summary
from services.platform.jobs.kind import JobKind


def summary(config: Mapping[str, Any]) -> str:
    """``3 runs in lockstep: SSSG rl_sparse seed 0, 40,000 steps, ...``."""
    runs = config.get("runs") or []
    if not runs:
        return "runs in lockstep"
    more = ", ..." if len(runs) > 1 else ""
    return f"{len(runs)} run(s) in lockstep: {run_summary(runs[0])}{more}"


KIND = JobKind(
    name="reproduce_batch",
    title="Lockstep batch of a reproduction's runs",
    config=None,
    summary=summary,
    counts_steps=True,
)
