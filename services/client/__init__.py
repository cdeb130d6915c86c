"""A small typed Python client of the platform's REST api (httpx), and what it returns."""

from services.client.client import DownloadedFile, PlatformClient
from services.client.errors import ChecksumMismatchError, PlatformError, WaitTimeoutError
from services.client.schemas import (
    FINAL_JOB_STATUSES,
    AccessToken,
    ApiToken,
    Artifact,
    Classifier,
    Curve,
    HFModel,
    Job,
    JobLog,
    JobLogEntry,
    LabSession,
    Page,
    Subject,
    User,
)

__all__ = [
    "FINAL_JOB_STATUSES",
    "AccessToken",
    "ApiToken",
    "Artifact",
    "ChecksumMismatchError",
    "Classifier",
    "Curve",
    "DownloadedFile",
    "HFModel",
    "Job",
    "JobLog",
    "JobLogEntry",
    "LabSession",
    "Page",
    "PlatformClient",
    "PlatformError",
    "Subject",
    "User",
    "WaitTimeoutError",
]
