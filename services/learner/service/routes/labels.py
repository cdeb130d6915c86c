"""Labels: the decoded feedback on each executed action, one Fhat update per label."""

from __future__ import annotations

from fastapi import APIRouter, BackgroundTasks

from services.learner.service.deps import SessionDep, StoreDep
from services.learner.service.schemas import (
    LabelCreate,
    LabelPrepare,
    LabelPreparePublic,
    LabelPublic,
)

router = APIRouter(prefix="/hf-sessions/{session_id}", tags=["labels"])


@router.post("/labels")
def add_label(
    body: LabelCreate, session: SessionDep, store: StoreDep, after: BackgroundTasks
) -> LabelPublic:
    """Store a label, update Fhat (1 + K_HF steps unless held out) and journal it.

    Idempotent by ``marker_id``: the same label sent again answers ``duplicate: true`` and
    changes nothing; a different label under a used marker id is a 409, and so is a new
    label once the budget is reached. With ``next_observation`` the answer also carries
    pi_HF's next action (sampled as ``POST /act`` samples it) unless the budget is full.
    The label is in the session's journal before the answer and synced to disk right after
    it (:meth:`SessionStore.persist <services.learner.service.store.SessionStore.persist>`).
    A label prepared with ``POST /labels/prepare`` (same marker id, observation, action,
    oracle truth and next observation, nothing else changed the session since) answers
    without running the update: ``prepared: true``, and the same session as otherwise.
    """
    outcome, next_action = store.add_label(
        session,
        next_observation=body.next_observation,
        marker_id=body.marker_id,
        observation=body.observation,
        action=body.action,
        correct=body.feedback == "correct",
        p_error=body.p_error,
        log_likelihood_ratio=body.log_likelihood_ratio,
        oracle_correct=body.oracle_correct,
    )
    after.add_task(store.persist, session)
    with session.lock:
        return LabelPublic(
            labels=len(session.labels),
            model_version=session.model_version,
            metrics=session.metrics(),
            done=session.done,
            duplicate=outcome.duplicate,
            validation=outcome.record.validation,
            next_action=next_action,
            prepared=outcome.prepared,
        )


@router.post("/labels/prepare")
def prepare_label(body: LabelPrepare, session: SessionDep, store: StoreDep) -> LabelPreparePublic:
    """Compute a label's update for both feedback values before the feedback is decoded.

    The session keeps one prepared label (a new one replaces it) until its next label or
    sampled action; the label with the same fields then only swaps the matching update in.
    The session itself does not change here.
    """
    prepared = store.prepare_label(session, **body.model_dump())
    return LabelPreparePublic(prepared=prepared)
