"""HF sessions: create, list, read."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter

from services.learner.feedback import FeedbackConfig
from services.learner.service.deps import SessionDep, StoreDep
from services.learner.service.schemas import HFSessionCreate, HFSessionPublic
from services.learner.service.session import HFSession

router = APIRouter(prefix="/hf-sessions", tags=["hf-sessions"])


def session_public(session: HFSession) -> HFSessionPublic:
    """The public view of ``session`` (taken under its lock)."""
    with session.lock:
        spec = session.spec
        return HFSessionPublic(
            id=spec.id,
            task=spec.task,
            map=spec.map,
            seed=spec.seed,
            method=spec.method,
            fhat=spec.fhat,
            label_budget=spec.label_budget,
            labels=len(session.labels),
            model_version=session.model_version,
            metrics=session.metrics(),
            done=session.done,
            created_at=spec.created_at,
        )


@router.post("", status_code=201)
def create_session(body: HFSessionCreate, store: StoreDep) -> HFSessionPublic:
    """Start an HF session: a fresh Fhat seeded as `bgrl reproduce`'s stage 2 for ``seed``."""
    fhat = FeedbackConfig(**body.fhat.overrides(), method=body.method)
    session = store.create(
        task=body.task,
        map_spec=body.map,
        seed=body.seed,
        label_budget=body.label_budget,
        method=body.method,
        fhat=asdict(fhat),
    )
    return session_public(session)


@router.get("")
def list_sessions(store: StoreDep) -> list[HFSessionPublic]:
    """Every HF session the service keeps, oldest first."""
    return [session_public(s) for s in store.list()]


@router.get("/{session_id}")
def read_session(session: SessionDep) -> HFSessionPublic:
    """One HF session."""
    return session_public(session)
