"""ErrP classifiers (made by calibration jobs): metrics and model files."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_RESPONSE, FormatQuery, model_response
from services.api.schemas.classifiers import ClassifierPublic
from services.api.schemas.common import MAX_ROW_ID, Page
from services.core.db.models import Classifier

router = APIRouter(
    prefix="/api/v1/classifiers", tags=["classifiers"], dependencies=[Depends(get_current_user)]
)


@router.get("")
def list_classifiers(
    db: DbDep, page: PageDep, subject_id: Annotated[int | None, Query(ge=1, le=MAX_ROW_ID)] = None
) -> Page[ClassifierPublic]:
    """Classifiers, newest first (optionally of one subject)."""
    query = select(Classifier).order_by(Classifier.id.desc())
    if subject_id is not None:
        query = query.where(Classifier.subject_id == subject_id)
    return Page[ClassifierPublic].model_validate(paginate(db, query, page))


@router.get("/{classifier_id}")
def read(classifier_id: RowId, db: DbDep) -> ClassifierPublic:
    """One classifier and its metrics."""
    return ClassifierPublic.model_validate(
        get_or_404(db, Classifier, classifier_id, "classifier_id")
    )


@router.get("/{classifier_id}/download", response_class=FileResponse, responses=CHECKSUM_RESPONSE)
def download(
    classifier_id: RowId, db: DbDep, store: StoreDep, model_format: FormatQuery = "onnx"
) -> FileResponse:
    """The classifier as ONNX, TorchScript or a torch.export program (pt2), with
    ``X-Checksum-Sha256``: preprocessed epochs in volts in, P(error) out."""
    clf = get_or_404(db, Classifier, classifier_id, "classifier_id")
    ids = {
        "torchscript": clf.torchscript_artifact_id,
        "pt2": clf.pt2_artifact_id,
        "onnx": clf.onnx_artifact_id,
    }
    return model_response(
        db,
        store,
        ids,
        model_format,
        what=f"classifier {classifier_id}",
        field="classifier_id",
        filename=f"classifier-{clf.id}",
    )
