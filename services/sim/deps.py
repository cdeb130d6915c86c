"""FastAPI dependencies of the sim service (``Annotated`` aliases used by the routes)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends
from starlette.requests import HTTPConnection

from services.sim.lsl_markers import MarkerPublisher
from services.sim.registry import SessionRegistry
from services.sim.sessions import SimSession
from services.sim.settings import SimSettings


def get_settings(connection: HTTPConnection) -> SimSettings:
    """The settings the app was built with."""
    return connection.app.state.settings


def get_registry(connection: HTTPConnection) -> SessionRegistry:
    """The app's session registry (created at start-up)."""
    return connection.app.state.registry


def get_publisher(connection: HTTPConnection) -> MarkerPublisher | None:
    """The LSL marker publisher, or None when markers are disabled."""
    return connection.app.state.publisher


def get_session(session_id: str, connection: HTTPConnection) -> SimSession:
    """The open session named in the path (404 unknown, 410 closed)."""
    return get_registry(connection).get(session_id)


SettingsDep = Annotated[SimSettings, Depends(get_settings)]
RegistryDep = Annotated[SessionRegistry, Depends(get_registry)]
PublisherDep = Annotated[MarkerPublisher | None, Depends(get_publisher)]
SessionDep = Annotated[SimSession, Depends(get_session)]
