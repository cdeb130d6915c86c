"""Classifiers: list, inspect, classify one preprocessed epoch."""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter

from services.core.feedback import is_error
from services.eeg.service.deps import ClassifiersDep
from services.eeg.service.errors import EpochMismatchError
from services.eeg.service.schemas import ClassifierPublic, EpochClassify, Feedback

router = APIRouter(prefix="/classifiers", tags=["classifiers"])

MAX_EPOCH_VOLTS = 1e-2
"""Largest |amplitude| accepted in a preprocessed epoch (10 mV): band-passed EEG stays far
below it, while the same epoch in microvolts exceeds it."""


@router.get("")
def list_classifiers(classifiers: ClassifiersDep) -> list[ClassifierPublic]:
    """Trained classifiers with their calibration metrics (unusable ones are left out)."""
    return classifiers.list()


@router.get("/{classifier_id}")
def read_classifier(classifier_id: str, classifiers: ClassifiersDep) -> ClassifierPublic:
    """One classifier."""
    return classifiers.public(classifier_id)


@router.post("/{classifier_id}/classify")
def classify_epoch(
    classifier_id: str, body: EpochClassify, classifiers: ClassifiersDep
) -> Feedback:
    """Classify one preprocessed epoch (volts); its shape, channels and rate must match."""
    clf = classifiers.get(classifier_id)
    if body.ch_names != clf.ch_names:
        missing = [c for c in clf.ch_names if c not in body.ch_names]
        raise EpochMismatchError(
            f"channels do not match the classifier's {len(clf.ch_names)} channels"
            + (f" (missing {', '.join(missing[:8])})" if missing else " (order differs)"),
            field="ch_names",
        )
    if not np.isclose(body.sfreq, clf.params.sfreq_out):
        raise EpochMismatchError(
            f"epoch rate {body.sfreq:g} Hz; the classifier takes {clf.params.sfreq_out:g} Hz",
            field="sfreq",
        )
    rows = {len(row) for row in body.epoch}
    if len(body.epoch) != clf.epoch_shape[0] or rows != {clf.epoch_shape[1]}:
        raise EpochMismatchError(
            f"epoch must be {clf.epoch_shape[0]} x {clf.epoch_shape[1]} (channels x times), "
            f"got {len(body.epoch)} rows of {sorted(rows)} samples",
            field="epoch",
        )
    X = np.asarray(body.epoch, dtype=np.float64)
    if not np.all(np.isfinite(X)):
        raise EpochMismatchError("epoch contains NaN or infinite values", field="epoch")
    peak = float(np.max(np.abs(X)))
    if peak > MAX_EPOCH_VOLTS:
        raise EpochMismatchError(
            f"epoch amplitudes reach {peak:.3g}, which looks like microvolts; send volts "
            f"(|x| <= {MAX_EPOCH_VOLTS:g})",
            field="epoch",
        )
    p_error, log_likelihood_ratio = clf.decode_epoch(X)
    return Feedback(
        status="ok",
        p_error=p_error,
        log_likelihood_ratio=log_likelihood_ratio,
        feedback="error" if is_error(p_error) else "correct",
        classifier_id=classifier_id,
        synthetic=clf.synthetic,
    )
