"""Human-feedback policies pi_HF: metrics and model files."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_RESPONSE, FormatQuery, model_response
from services.api.schemas.common import Page
from services.api.schemas.hf_models import HFModelPublic
from services.core.db.models import HFModel

router = APIRouter(
    prefix="/api/v1/hf-models", tags=["hf-models"], dependencies=[Depends(get_current_user)]
)


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
    hf_model_id: RowId, db: DbDep, store: StoreDep, model_format: FormatQuery = "torchscript"
) -> FileResponse:
    """The policy as TorchScript, a torch.export program (pt2) or ONNX, with
    ``X-Checksum-Sha256``: raw float observations in, Fhat's logits out (greedy pi_HF: their
    argmax)."""
    model = get_or_404(db, HFModel, hf_model_id, "hf_model_id")
    ids = {
        "torchscript": model.torchscript_artifact_id,
        "pt2": model.pt2_artifact_id,
        "onnx": model.onnx_artifact_id,
    }
    return model_response(
        db,
        store,
        ids,
        model_format,
        what=f"HF model {hf_model_id}",
        field="hf_model_id",
        filename=f"hf-model-{model.id}",
    )
