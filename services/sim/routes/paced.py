"""The paced mode: one action per period (1.5 s by default) for human observers."""

from __future__ import annotations

from fastapi import APIRouter, status

from services.core.actions import Action
from services.sim.deps import SessionDep, SettingsDep
from services.sim.schemas import PacedCreate, PacedPublic, QueuePublic, QueueRequest

router = APIRouter(prefix="/sessions/{session_id}/paced", tags=["paced"])


@router.post("", status_code=status.HTTP_201_CREATED)
def start_paced(body: PacedCreate, session: SessionDep, settings: SettingsDep) -> PacedPublic:
    """Start executing actions on a clock: random, oracle, or the client's queued actions."""
    paced = session.start_paced(
        body.policy,
        period_s=body.period_s or settings.paced_action_period_s,
        auto_reset=body.auto_reset,
        max_actions=body.max_actions,
    )
    return PacedPublic.model_validate(paced)


@router.get("")
def read_paced(session: SessionDep) -> PacedPublic:
    """State of the paced mode (running, actions executed, queue length, last error)."""
    return PacedPublic.model_validate(session.paced_status())


@router.delete("")
def stop_paced(session: SessionDep) -> PacedPublic:
    """Stop the paced mode; manual stepping is allowed again."""
    return PacedPublic.model_validate(session.stop_paced())


@router.post("/actions")
def queue_actions(body: QueueRequest, session: SessionDep) -> QueuePublic:
    """Append actions for the ``queue`` policy (they may be queued before it starts)."""
    return QueuePublic(queued_actions=session.enqueue([Action(a) for a in body.actions]))


@router.delete("/actions")
def clear_actions(session: SessionDep) -> QueuePublic:
    """Drop every queued action."""
    session.clear_queue()
    return QueuePublic(queued_actions=0)
