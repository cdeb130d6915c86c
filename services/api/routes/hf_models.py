"""Human-feedback policies pi_HF: metrics and model files."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_RESPONSE, artifact_response
from services.api.schemas.common import Page
from services.api.schemas.hf_models import HFModelPublic
from services.core.db.models import Artifact, HFModel
from services.core.errors import NotFoundError

router = APIRouter(
    prefix="/api/v1/hf-models", tags=["hf-models"], dependencies=[Depends(get_current_user)]
)

ModelFormat = Literal["torchscript", "onnx"]
SUFFIXES = {"onnx": ".onnx", "torchscript": ".pt"}


@router.get("")
def list_hf_models(
    db: DbDep, page: PageDep, task: Annotated[Literal["sssg", "vssg"] | None, Query()] = None
) -> Page[HFModelPublic]:
    """Human-feedback policies, newest first (optionally of one task)."""
    query = select(HFModel).order_by(HFModel.id.desc())
    if task is not None:
        query = query.where(HFModel.task == task)
    return Page[HFModelPublic].model_validate(paginate(db, query, page))


@router.get("/{hf_model_id}")
def read(hf_model_id: RowId, db: DbDep) -> HFModelPublic:
    """One human-feedback policy and its metrics."""
    return HFModelPublic.model_validate(get_or_404(db, HFModel, hf_model_id, "hf_model_id"))


@router.get("/{hf_model_id}/download", response_class=FileResponse, responses=CHECKSUM_RESPONSE)
def download(
    hf_model_id: RowId,
    db: DbDep,
    store: StoreDep,
    model_format: Annotated[ModelFormat, Query(alias="format")] = "torchscript",
) -> FileResponse:
    """The policy as TorchScript or ONNX, with ``X-Checksum-Sha256``."""
    model = get_or_404(db, HFModel, hf_model_id, "hf_model_id")
    artifact_id = (
        model.torchscript_artifact_id if model_format == "torchscript" else model.onnx_artifact_id
    )
    if artifact_id is None:
        raise NotFoundError(f"HF model {hf_model_id} has no {model_format} file", field="format")
    artifact = get_or_404(db, Artifact, artifact_id, "hf_model_id")
    return artifact_response(store, artifact, f"hf-model-{model.id}{SUFFIXES[model_format]}")
