"""Every job kind, by name: the one list the api, the worker, the client and the CLI read.

A new kind is one module here (its config model, its summary, its :class:`JobKind`) added to
:data:`JOB_KINDS` and ``SubmittedKindName``, plus its handler registered in the worker
(``services.worker.app.HANDLERS``). A test fails if a kind's name is spelled anywhere
outside this package.
"""

from __future__ import annotations

from typing import Literal, get_args

from services.platform.jobs import (
    bids_export,
    eeg_calibration,
    guided_ppo,
    live_session,
    reproduce,
    reproduce_batch,
    reproduce_run,
    session_replay,
)
from services.platform.jobs.kind import JobKind

GUIDED_PPO = guided_ppo.KIND
REPRODUCE = reproduce.KIND
REPRODUCE_RUN = reproduce_run.KIND
REPRODUCE_BATCH = reproduce_batch.KIND
EEG_CALIBRATION = eeg_calibration.KIND
LIVE_SESSION = live_session.KIND
BIDS_EXPORT = bids_export.KIND
SESSION_REPLAY = session_replay.KIND

JOB_KINDS: dict[str, JobKind] = {
    kind.name: kind
    for kind in (
        GUIDED_PPO,
        REPRODUCE,
        REPRODUCE_RUN,
        REPRODUCE_BATCH,
        EEG_CALIBRATION,
        LIVE_SESSION,
        BIDS_EXPORT,
        SESSION_REPLAY,
    )
}
"""Every kind by name, in the order the dashboard and the CLI list them."""

SubmittedKindName = Literal[
    "guided_ppo", "reproduce", "eeg_calibration", "bids_export", "session_replay"
]
"""Kinds a user may submit (for type hints; equal to the submittable kinds of
:data:`JOB_KINDS`)."""
KindName = Literal[
    "guided_ppo",
    "reproduce",
    "reproduce_run",
    "reproduce_batch",
    "eeg_calibration",
    "live_session",
    "bids_export",
    "session_replay",
]
"""Every kind (what the job list filters on), in :data:`JOB_KINDS`' order."""
SUBMITTED_KINDS: tuple[str, ...] = get_args(SubmittedKindName)
KIND_NAMES: tuple[str, ...] = get_args(KindName)
assert tuple(JOB_KINDS) == KIND_NAMES
assert tuple(k.name for k in JOB_KINDS.values() if k.submittable) == SUBMITTED_KINDS


def job_kind(name: str) -> JobKind:
    """The kind called ``name`` (a ValueError listing the kinds if there is none)."""
    try:
        return JOB_KINDS[name]
    except KeyError:
        raise ValueError(f"unknown job kind {name!r}; use one of {', '.join(JOB_KINDS)}") from None
