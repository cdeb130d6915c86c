"""FastAPI dependencies of the learner service (``Annotated`` aliases used by the routes)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection

from services.learner.service.session import HFSession
from services.learner.service.settings import LearnerSettings
from services.learner.service.store import SessionStore


def get_settings(connection: HTTPConnection) -> LearnerSettings:
    """The settings the app was built with."""
    return connection.app.state.settings


def get_store(connection: HTTPConnection) -> SessionStore:
    """The app's session store (loaded at start-up)."""
    return connection.app.state.store


def get_session(session_id: str, connection: HTTPConnection) -> HFSession:
    """The HF session named in the path (404 unknown)."""
    return get_store(connection).get(session_id)


SettingsDep = Annotated[LearnerSettings, Depends(get_settings)]
StoreDep = Annotated[SessionStore, Depends(get_store)]
SessionDep = Annotated[HFSession, Depends(get_session)]
