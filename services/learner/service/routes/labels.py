"""Labels: the decoded feedback on each executed action, one Fhat update per label."""

from __future__ import annotations

from fastapi import APIRouter

from services.learner.service.deps import SessionDep, StoreDep
from services.learner.service.schemas import LabelCreate, LabelPublic

router = APIRouter(prefix="/hf-sessions/{session_id}", tags=["labels"])


@router.post("/labels")
def add_label(body: LabelCreate, session: SessionDep, store: StoreDep) -> LabelPublic:
    """Store a label, update Fhat (1 + K_HF steps unless held out) and checkpoint.

    Idempotent by ``marker_id``: the same label sent again answers ``duplicate: true`` and
    changes nothing; a different label under a used marker id is a 409, and so is a new
    label once the budget is reached. With ``next_observation`` the answer also carries
    pi_HF's next action (sampled as ``POST /act`` samples it) unless the budget is full.
    """
    outcome = store.add_label(
        session,
        marker_id=body.marker_id,
        observation=body.observation,
        action=body.action,
        correct=body.feedback == "correct",
        p_error=body.p_error,
        oracle_correct=body.oracle_correct,
    )
    next_action = None
    if body.next_observation is not None and not session.done:
        next_action, _ = store.act(session, body.next_observation, greedy=False)
    with session.lock:
        return LabelPublic(
            labels=len(session.labels),
            model_version=session.model_version,
            metrics=session.metrics(),
            done=session.done,
            duplicate=outcome.duplicate,
            validation=outcome.record.validation,
            next_action=next_action,
        )
