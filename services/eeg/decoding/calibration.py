"""ErrP calibration: train and evaluate ErrP decoders on a labelled recording (paper stage 1).

Stratified, seeded 80/12/8 train/validation/test split of the epochs (EEG trials)
(:mod:`services.eeg.decoding.split`). On that split: EEGNet, the paper's decoder
(class-weighted cross-entropy, Adam, early stopping on the validation loss:
:mod:`services.eeg.decoding.eegnet_training`), and beside it the classical window-mean
shrinkage LDA (:mod:`services.eeg.decoding.classical`) and xDAWN + Riemannian geometry
(:mod:`services.eeg.decoding.riemannian`) (:mod:`services.eeg.decoding.decoders`). The
decoder with the higher validation accuracy is kept (EEGNet, then the sLDA, on a tie): it
is the classifier, and its test metrics are the calibration's (test accuracy, balanced
accuracy, ROC AUC, confusion matrix: :mod:`services.eeg.decoding.metrics`);
``metrics["decoders"]`` has every decoder's. The kept decoder's P(error) is calibrated on
the validation epochs (Platt scaling, :mod:`services.eeg.decoding.posterior`): the
classifier carries the calibration, ``metrics["calibration"]`` has its fit and the test
epochs' expected calibration error and reliability bins. ``calibrate(..., out_dir=DIR)``
writes the classifier, ``metrics.json``, ``history.json`` and the calibration report
(:mod:`services.eeg.decoding.outputs`).

Words: an *epoch* is one EEG trial (the window after an action); a *pass* is one sweep of
training over the training epochs.

Safe in a long-running, multi-threaded process: all randomness comes from local
generators seeded with ``seed`` (numpy ``Generator``, ``torch.Generator`` for weights,
dropout and minibatch order), so neither torch's global generator nor its thread count is
touched; the results equal those of seeding the global generator with ``seed``.

This module is the calibration's public API; the names it imports from the modules above
are re-exported here (``__all__``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from services.eeg.decoding.decoders import fit_decoders, select_decoder
from services.eeg.decoding.metrics import classification_metrics, roc_auc
from services.eeg.decoding.outputs import HISTORY_FILE, METRICS_FILE, write_outputs
from services.eeg.decoding.posterior import calibration_report, fit_platt
from services.eeg.decoding.result import CalibrationResult
from services.eeg.decoding.split import SPLIT_FRACTIONS, Split, stratified_split
from services.eeg.decoding.training_config import DECODERS, CalibrationCancelled, TrainingConfig
from services.eeg.recordings.epochs import EpochSet, epochs_from_raw
from services.eeg.signal.preprocessing import PreprocessingParams

if TYPE_CHECKING:
    import mne

__all__ = [
    "DECODERS",
    "HISTORY_FILE",
    "METRICS_FILE",
    "SPLIT_FRACTIONS",
    "CalibrationCancelled",
    "CalibrationResult",
    "Split",
    "TrainingConfig",
    "calibrate",
    "classification_metrics",
    "roc_auc",
    "stratified_split",
    "train_classifier",
]


def train_classifier(
    epochs: EpochSet,
    *,
    seed: int = 0,
    config: TrainingConfig | None = None,
    split: Split | None = None,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
) -> CalibrationResult:
    """Train the decoders of ``config.decoders`` on one split and keep the best on validation.

    Every decoder sees the same training epochs (scaled by 1 / their SD); the one with the
    higher validation accuracy is kept (earlier in :data:`DECODERS` on a tie) and evaluated
    on the held-out test split.

    Parameters
    ----------
    epochs : EpochSet
        Labelled epochs (1 = error).
    seed : int
        Seeds the split, EEGNet's weight initialisation and minibatch order, and the
        classical decoders' cross-validation folds.
    config : TrainingConfig | None
        Hyperparameters and decoders; defaults to :class:`TrainingConfig`.
    split : Split | None
        Use these indices instead of :func:`stratified_split`.
    progress : bool
        Show a tqdm bar over training passes.
    should_stop : callable | None
        Called before every training pass and before each classical fit; when it returns
        True, :class:`CalibrationCancelled` is raised.

    Returns
    -------
    CalibrationResult
        Without ``out_dir``; nothing is written.
    """
    config = config or TrainingConfig()
    y_all = epochs.y
    if len(np.unique(y_all)) < 2:
        raise ValueError("calibration needs both correct and error epochs")
    if len(epochs) < 30:
        raise ValueError(f"calibration needs at least 30 epochs, got {len(epochs)}")
    split = split or stratified_split(y_all, seed=seed)
    input_scale = 1.0 / float(epochs.X[split.train].std())
    t0 = time.perf_counter()
    fits = fit_decoders(
        epochs,
        split,
        input_scale,
        seed=seed,
        config=config,
        progress=progress,
        should_stop=should_stop,
    )
    decoders = {name: fit.metrics for name, fit in fits.items()}
    kept = select_decoder(decoders)
    eegnet = fits.get("eegnet")
    test_proba = fits[kept].test_proba
    posterior = fit_platt(y_all[split.val], fits[kept].val_proba)
    metrics = classification_metrics(y_all[split.test], test_proba)
    metrics.update(
        {
            "decoder": kept,
            "selected_by": "validation accuracy",
            "decoders": decoders,
            "n_epochs": len(epochs),
            "n_params": decoders[kept]["n_params"],
            "n_train": int(split.train.size),
            "n_val": int(split.val.size),
            "n_test": int(split.test.size),
            "error_fraction": float(y_all.mean()),
            **(eegnet.facts if eegnet else {}),
            "train_seconds": time.perf_counter() - t0,
            "seed": seed,
            "synthetic": epochs.synthetic,
            "training_config": asdict(config),
            "calibration": calibration_report(posterior, y_all[split.test], test_proba),
        }
    )
    classifier = fits[kept].classifier
    classifier.metrics = metrics
    classifier.calibration = posterior
    history = eegnet.history if eegnet else {"train_loss": [], "val_loss": [], "val_accuracy": []}
    return CalibrationResult(
        classifier=classifier,
        metrics=metrics,
        history=history,
        split=split,
        epochs=epochs,
        test_proba=test_proba,
        candidates={name: fit.classifier for name, fit in fits.items()},
    )


def calibrate(
    data: mne.io.BaseRaw | EpochSet,
    *,
    seed: int = 0,
    out_dir: str | Path | None = None,
    config: TrainingConfig | None = None,
    params: PreprocessingParams | None = None,
    report: bool = True,
    onnx: bool = False,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
) -> CalibrationResult:
    """Preprocess (if given a recording), train, evaluate and save an ErrP classifier.

    Parameters
    ----------
    data : mne.io.BaseRaw | EpochSet
        A labelled calibration recording (Status codes 1/2) or epochs made from one. A
        recording may be read lazily: it is preprocessed in chunks.
    seed : int
        Seeds the split, initialisation, dropout and minibatch order.
    out_dir : str | Path | None
        If given, write the classifier, ``metrics.json``, ``history.json`` and (with
        ``report``) ``report.png``/``report.html`` there. The files are written to a
        temporary sibling folder and moved in at the end (``metrics.json`` last); on any
        failure or cancellation that folder is removed and ``out_dir`` is left as it was.
    config : TrainingConfig | None
        Training hyperparameters.
    params : PreprocessingParams | None
        Preprocessing for a recording (ignored for an EpochSet).
    report : bool
        Write the calibration report.
    onnx : bool
        Also export ``model.onnx`` (a few seconds) when the kept decoder has an ONNX form
        (EEGNet and the sLDA; xDAWN + RG has none).
    progress : bool
        Show progress bars.
    should_stop : callable | None
        Polled before preprocessing, before every training pass and before each classical
        fit (e.g. a job's cancel flag); True raises :class:`CalibrationCancelled`.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationCancelled
        When ``should_stop()`` returned True.
    """
    if should_stop is not None and should_stop():
        raise CalibrationCancelled("calibration cancelled before it started")
    if isinstance(data, EpochSet):
        epochs = data
    else:
        epochs = epochs_from_raw(data, params, progress=progress)
    result = train_classifier(
        epochs, seed=seed, config=config, progress=progress, should_stop=should_stop
    )
    if out_dir is not None:
        result.out_dir = write_outputs(result, Path(out_dir), report=report, onnx=onnx)
    return result
