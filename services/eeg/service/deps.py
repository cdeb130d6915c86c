"""FastAPI dependencies of the EEG service (``Annotated`` aliases used by the routes)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection

from services.eeg.service.jobs import JobRunner
from services.eeg.service.settings import EEGSettings
from services.eeg.service.state import EEGService
from services.eeg.service.store import ClassifierStore, JobStore, RecordingStore


def get_settings(connection: HTTPConnection) -> EEGSettings:
    """The settings the app was built with."""
    return connection.app.state.settings


def get_service(connection: HTTPConnection) -> EEGService:
    """The app's service state (created at start-up)."""
    return connection.app.state.service


def get_recordings(connection: HTTPConnection) -> RecordingStore:
    """The stored recordings."""
    return get_service(connection).recordings


def get_classifiers(connection: HTTPConnection) -> ClassifierStore:
    """The trained classifiers."""
    return get_service(connection).classifiers


def get_jobs(connection: HTTPConnection) -> JobStore:
    """The job records."""
    return get_service(connection).jobs


def get_runner(connection: HTTPConnection) -> JobRunner:
    """The calibration job runner."""
    return get_service(connection).runner


SettingsDep = Annotated[EEGSettings, Depends(get_settings)]
ServiceDep = Annotated[EEGService, Depends(get_service)]
RecordingsDep = Annotated[RecordingStore, Depends(get_recordings)]
ClassifiersDep = Annotated[ClassifierStore, Depends(get_classifiers)]
JobsDep = Annotated[JobStore, Depends(get_jobs)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]
