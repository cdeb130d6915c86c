"""The job contract: each job kind's config model (the one validation of a job's config,
used by the api before it queues a job and by the worker before it runs it) and its display
summary, in one registry (:mod:`services.platform.jobs.registry`)."""

from services.platform.jobs.kind import JobConfig, JobKind, config_error
from services.platform.jobs.registry import (
    BIDS_EXPORT,
    EEG_CALIBRATION,
    GUIDED_PPO,
    JOB_KINDS,
    KIND_NAMES,
    LIVE_SESSION,
    REPRODUCE,
    REPRODUCE_BATCH,
    REPRODUCE_RUN,
    SESSION_REPLAY,
    SUBMITTED_KINDS,
    KindName,
    SubmittedKindName,
    job_kind,
)

__all__ = [
    "BIDS_EXPORT",
    "EEG_CALIBRATION",
    "GUIDED_PPO",
    "JOB_KINDS",
    "KIND_NAMES",
    "LIVE_SESSION",
    "REPRODUCE",
    "REPRODUCE_BATCH",
    "REPRODUCE_RUN",
    "SESSION_REPLAY",
    "SUBMITTED_KINDS",
    "JobConfig",
    "JobKind",
    "KindName",
    "SubmittedKindName",
    "config_error",
    "job_kind",
]
