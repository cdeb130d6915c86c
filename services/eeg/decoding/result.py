"""What a calibration returns: the kept classifier, its metrics, history, split and epochs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.decoding.split import Split
from services.eeg.recordings.epochs import EpochSet


@dataclass
class CalibrationResult:
    """Outcome of :func:`~services.eeg.decoding.calibration.calibrate`.

    Attributes
    ----------
    classifier : ErrPClassifier
        The kept decoder's classifier (the better on validation).
    metrics : dict
        Test metrics and run facts (also in ``metrics.json``).
    history : dict of list
        EEGNet's per-pass ``train_loss``, ``val_loss``, ``val_accuracy`` (empty lists
        without EEGNet).
    split : Split
        Indices into ``epochs``.
    epochs : EpochSet
        The data set that was used.
    out_dir : Path or None
        Where the artefacts were written.
    test_proba : ndarray
        P(error) of the kept decoder for the test epochs (in ``split.test`` order).
    candidates : dict of ErrPClassifier
        Every trained decoder by name (``eegnet``, ``lda``, ``xdawn_rg``), the kept one
        included.
    """

    classifier: ErrPClassifier
    metrics: dict[str, Any]
    history: dict[str, list[float]]
    split: Split
    epochs: EpochSet
    out_dir: Path | None = None
    test_proba: np.ndarray = field(default_factory=lambda: np.empty(0))
    candidates: dict[str, ErrPClassifier] = field(default_factory=dict)
