"""Sessions: open, list, inspect, close, reset and step."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from services.core.actions import Action
from services.core.markers import ActionMarker
from services.sim.deps import RegistryDep, SessionDep
from services.sim.schemas import (
    ResetPublic,
    ResetRequest,
    SessionCreate,
    SessionPublic,
    StepPublic,
    StepRequest,
)

router = APIRouter(prefix="/sessions", tags=["sessions"])


@router.post("", status_code=status.HTTP_201_CREATED)
def create_session(body: SessionCreate, registry: RegistryDep) -> SessionPublic:
    """Open a session on a shipped or configured map and reset it with ``seed``."""
    session = registry.create(
        task=body.task, reward_mode=body.reward_mode, map_spec=body.map, seed=body.seed
    )
    return SessionPublic.model_validate(session.snapshot())


@router.get("")
def list_sessions(registry: RegistryDep) -> list[SessionPublic]:
    """Every open session."""
    return [SessionPublic.model_validate(s.snapshot()) for s in registry.list()]


@router.get("/{session_id}")
def read_session(session: SessionDep) -> SessionPublic:
    """The session's current state (pose, last observation, last marker, paced mode)."""
    return SessionPublic.model_validate(session.snapshot())


@router.delete("/{session_id}", status_code=status.HTTP_204_NO_CONTENT)
def close_session(session: SessionDep, registry: RegistryDep) -> Response:
    """Stop the paced mode, release the env; the id answers 410 afterwards."""
    registry.close(session.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post("/{session_id}/reset")
def reset_session(session: SessionDep, body: ResetRequest | None = None) -> ResetPublic:
    """Start a new episode (refused while the paced mode runs)."""
    observation, info = session.reset(body.seed if body is not None else None)
    return ResetPublic(episode=session.episode, observation=observation, info=info)


@router.post("/{session_id}/step")
def step_session(body: StepRequest, session: SessionDep) -> StepPublic:
    """Execute one action; the response carries its LSL timestamp and oracle verdict."""
    outcome = session.step(Action(body.action))
    return StepPublic(
        observation=outcome.observation,
        reward=outcome.reward,
        terminated=outcome.terminated,
        truncated=outcome.truncated,
        info=outcome.info,
        timestamp=outcome.marker.timestamp,
        marker=outcome.marker,
    )


@router.get("/{session_id}/markers")
def list_markers(
    session: SessionDep,
    since_step: Annotated[int, Query(ge=0, description="First step to return.")] = 0,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> list[ActionMarker]:
    """The session's action markers from ``since_step`` on, oldest first (the same markers
    as on the LSL stream; the last 10,000 are kept)."""
    return session.markers(since_step, limit)
