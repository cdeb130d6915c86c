"""The decoders calibration trains on one split, and the rule that keeps one of them.

Every decoder sees the same training epochs, scaled by the same 1 / (training SD), and is
bound with the same channel list, preprocessing and input rate into an
:class:`~services.eeg.decoding.classifier.ErrPClassifier`: EEGNet (the paper's,
:mod:`services.eeg.decoding.eegnet_training`), the window-mean shrinkage LDA
(:mod:`services.eeg.decoding.classical`) and xDAWN + Riemannian geometry
(:mod:`services.eeg.decoding.riemannian`). The one with the higher validation accuracy is kept.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from torch import nn

from services.eeg.decoding.classical import N_CV_FOLDS, fit_window_lda
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.decoding.eegnet import count_parameters
from services.eeg.decoding.eegnet_training import train_eegnet
from services.eeg.decoding.metrics import validation_and_test_metrics
from services.eeg.decoding.riemannian import fit_xdawn_riemann
from services.eeg.decoding.split import Split
from services.eeg.decoding.training_config import DECODERS, CalibrationCancelled, TrainingConfig
from services.eeg.recordings.epochs import EpochSet


@dataclass
class DecoderFit:
    """One decoder trained on the split."""

    classifier: ErrPClassifier
    metrics: dict[str, Any]
    """Validation and test metrics, ``n_params`` and the decoder's own facts (CV, ...)."""
    test_proba: np.ndarray
    """P(error) on the test epochs (in ``split.test`` order)."""
    val_proba: np.ndarray
    """P(error) on the validation epochs (in ``split.val`` order): the posterior calibration
    is fitted on them (:mod:`services.eeg.decoding.posterior`)."""
    history: dict[str, list[float]] = field(default_factory=dict)
    """EEGNet's per-pass curves (empty for the others)."""
    facts: dict[str, Any] = field(default_factory=dict)
    """EEGNet's ``best_pass``, ``passes_run``, ``best_val_loss`` (empty for the others)."""


def fit_decoders(
    epochs: EpochSet,
    split: Split,
    input_scale: float,
    *,
    seed: int,
    config: TrainingConfig,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
) -> dict[str, DecoderFit]:
    """Train every decoder of ``config.decoders`` on ``split`` (in :data:`DECODERS` order).

    ``should_stop`` is polled before every EEGNet pass and before each classical fit.
    """

    def bind(model: nn.Module) -> ErrPClassifier:
        return ErrPClassifier(
            model,
            epochs.params,
            epochs.ch_names,
            epochs.sfreq_in,
            input_scale,
            synthetic=epochs.synthetic,
        )

    y_val, y_test = epochs.y[split.val], epochs.y[split.test]
    fits: dict[str, DecoderFit] = {}
    for name in (d for d in DECODERS if d in config.decoders):
        if name == "eegnet":
            eegnet = train_eegnet(
                epochs,
                split,
                input_scale,
                seed=seed,
                config=config,
                progress=progress,
                should_stop=should_stop,
            )
            metrics = validation_and_test_metrics(
                y_val, eegnet.val_proba, y_test, eegnet.test_proba
            )
            metrics["n_params"] = count_parameters(eegnet.model)
            fits[name] = DecoderFit(
                bind(eegnet.model),
                metrics,
                eegnet.test_proba,
                eegnet.val_proba,
                eegnet.history,
                eegnet.facts,
            )
            continue
        if should_stop is not None and should_stop():
            raise CalibrationCancelled(f"calibration cancelled before the {name} fit")
        train_X = (epochs.X[split.train] * input_scale).astype(np.float32)
        y_train = epochs.y[split.train]
        if name == "lda":
            lda = fit_window_lda(
                train_X, y_train, epochs.ch_names, epochs.params.sfreq_out, seed=seed
            )
            model, cv_accuracy, own = lda.model, lda.cv_accuracy, {"channels": lda.channels}
        else:  # xdawn_rg
            xdawn = fit_xdawn_riemann(train_X, y_train, seed=seed)
            model, cv_accuracy = xdawn.model, xdawn.cv_accuracy
            own = {"n_filters": model.n_filters}
        classifier = bind(model)
        test_proba = classifier.predict_proba(epochs.X[split.test])
        val_proba = classifier.predict_proba(epochs.X[split.val])
        metrics = validation_and_test_metrics(y_val, val_proba, y_test, test_proba)
        metrics.update(
            {
                "n_params": count_parameters(model),
                "cv_folds": N_CV_FOLDS,
                "cv_accuracy_mean": float(np.mean(cv_accuracy)),
                "cv_accuracy_std": float(np.std(cv_accuracy)),
                **own,
            }
        )
        fits[name] = DecoderFit(classifier, metrics, test_proba, val_proba)
    return fits


def select_decoder(metrics: Mapping[str, Mapping[str, Any]]) -> str:
    """The decoder with the highest validation accuracy; ties go to the earlier in
    :data:`DECODERS` (EEGNet first)."""
    return max(metrics, key=lambda d: (metrics[d]["val_accuracy"], -DECODERS.index(d)))
