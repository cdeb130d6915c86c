"""pi_HF: the next action in a state, and its export (TorchScript, .pt2, ONNX)."""

from __future__ import annotations

from fastapi import APIRouter, BackgroundTasks

from services.learner.service.deps import SessionDep, StoreDep
from services.learner.service.schemas import (
    ActPublic,
    ActRequest,
    ExportedFile,
    ExportPublic,
    ExportRequest,
)

router = APIRouter(prefix="/hf-sessions/{session_id}", tags=["policy"])


@router.post("/act")
def act(
    body: ActRequest, session: SessionDep, store: StoreDep, after: BackgroundTasks
) -> ActPublic:
    """pi_HF's action: sampled while collecting labels (default; journaled, as a label is)
    or greedy (changes nothing)."""
    action, version = store.act(session, body.observation, body.greedy)
    if not body.greedy:
        after.add_task(store.persist, session)
    return ActPublic(action=action, model_version=version, greedy=body.greedy)


@router.post("/export")
def export(body: ExportRequest, session: SessionDep, store: StoreDep) -> ExportPublic:
    """Write the greedy pi_HF as TorchScript, ``.pt2`` and ONNX into the platform's artifact
    store."""
    stored, version, metrics = store.export(session)
    return ExportPublic(
        files={
            fmt: ExportedFile(relpath=f.relpath, sha256=f.sha256, size_bytes=f.size_bytes)
            for fmt, f in stored.items()
        },
        model_version=version,
        metrics=metrics,
    )
