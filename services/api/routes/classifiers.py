"""ErrP classifiers (made by calibration jobs): metrics and model files."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import FileResponse
from sqlalchemy import select

from services.api.crud import get_or_404, paginate
from services.api.deps import DbDep, PageDep, RowId, StoreDep, get_current_user
from services.api.downloads import CHECKSUM_RESPONSE, artifact_response
from services.api.schemas.classifiers import ClassifierPublic
from services.api.schemas.common import MAX_ROW_ID, Page
from services.core.db.models import Artifact, Classifier
from services.core.errors import NotFoundError

router = APIRouter(
    prefix="/api/v1/classifiers", tags=["classifiers"], dependencies=[Depends(get_current_user)]
)

ModelFormat = Literal["onnx", "torchscript"]
SUFFIXES = {"onnx": ".onnx", "torchscript": ".pt"}


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
    classifier_id: RowId,
    db: DbDep,
    store: StoreDep,
    model_format: Annotated[ModelFormat, Query(alias="format")] = "onnx",
) -> FileResponse:
    """The classifier as ONNX or TorchScript, with ``X-Checksum-Sha256``."""
    clf = get_or_404(db, Classifier, classifier_id, "classifier_id")
    artifact_id = clf.onnx_artifact_id if model_format == "onnx" else clf.torchscript_artifact_id
    if artifact_id is None:
        raise NotFoundError(
            f"classifier {classifier_id} has no {model_format} file", field="format"
        )
    artifact = get_or_404(db, Artifact, artifact_id, "classifier_id")
    return artifact_response(store, artifact, f"classifier-{clf.id}{SUFFIXES[model_format]}")
