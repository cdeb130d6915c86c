"""ErrP calibration: train and evaluate ErrP decoders on a labelled recording (paper stage 1).

Stratified, seeded 80/12/8 train/validation/test split of the epochs (EEG trials). EEGNet
(the paper's): class-weighted cross-entropy (errors are the minority class); Adam; early
stopping on the validation loss (the weights of the best training pass are kept). Beside
it, on the same split, the classical window-mean shrinkage LDA
(:mod:`services.eeg.classical`). The decoder with the higher validation accuracy is kept
(EEGNet on a tie): it is the classifier, and its test metrics are the calibration's (test
accuracy, balanced accuracy, ROC AUC, confusion matrix); ``metrics["decoders"]`` has both.
``calibrate(..., out_dir=DIR)`` writes the classifier, ``metrics.json``, ``history.json``
and the calibration report.

Words: an *epoch* is one EEG trial (the window after an action); a *pass* is one sweep of
training over the training epochs.

Safe in a long-running, multi-threaded process: all randomness comes from local
generators seeded with ``seed`` (numpy ``Generator``, ``torch.Generator`` for weights,
dropout and minibatch order), so neither torch's global generator nor its thread count is
touched; the results equal those of seeding the global generator with ``seed``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from services.eeg.classical import N_CV_FOLDS, fit_window_lda
from services.eeg.classifier import (
    CONFIG_FILE,
    ONNX_FILE,
    STATE_FILE,
    TORCHSCRIPT_FILE,
    ErrPClassifier,
)
from services.eeg.eegnet import EEGNet, count_parameters
from services.eeg.preprocessing import EpochSet, PreprocessingParams, epochs_from_raw

if TYPE_CHECKING:
    import mne

SPLIT_FRACTIONS = (0.80, 0.12, 0.08)
"""Train / validation / test fractions (paper §EEG Classifier Training)."""
DECODERS = ("eegnet", "lda")
"""Decoders calibration can train: EEGNet and the window-mean shrinkage LDA."""
METRICS_FILE = "metrics.json"
HISTORY_FILE = "history.json"


_ARTEFACTS = frozenset(
    {
        CONFIG_FILE,
        STATE_FILE,
        TORCHSCRIPT_FILE,
        ONNX_FILE,
        HISTORY_FILE,
        "report.png",
        "report.html",
    }
)
"""Files a calibration writes besides ``metrics.json`` (report names: services.eeg.report)."""


class CalibrationCancelled(Exception):  # noqa: N818 (the name callers catch)
    """``should_stop()`` returned True: calibration stopped between two training passes."""


@dataclass(frozen=True)
class TrainingConfig:
    """Hyperparameters of calibration training."""

    lr: float = 1e-3
    """Adam learning rate."""
    weight_decay: float = 0.0
    """Adam L2 penalty."""
    batch_size: int = 32
    """Minibatch size."""
    max_passes: int = 300
    """Upper bound on training passes over the training split."""
    patience: int = 40
    """Stop after this many passes without a lower validation loss."""
    drop_prob: float = 0.25
    """EEGNet dropout probability."""
    kernel_length: int = 32
    """EEGNet temporal kernel length (samples at the feature rate)."""
    decoders: tuple[str, ...] = DECODERS
    """Decoders trained on the same split; the best on validation is kept."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "decoders", tuple(self.decoders))
        unknown = [d for d in self.decoders if d not in DECODERS]
        if not self.decoders or unknown or len(set(self.decoders)) < len(self.decoders):
            raise ValueError(
                f"decoders must be distinct names from {DECODERS}, got {self.decoders}"
            )


@dataclass
class Split:
    """Indices of the train, validation and test epochs."""

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray


@dataclass
class CalibrationResult:
    """Outcome of :func:`calibrate`.

    Attributes
    ----------
    classifier : ErrPClassifier
        The kept decoder's classifier (the better on validation).
    metrics : dict
        Test metrics and run facts (also in ``metrics.json``).
    history : dict of list
        Per-pass ``train_loss``, ``val_loss``, ``val_accuracy``.
    split : Split
        Indices into ``epochs``.
    epochs : EpochSet
        The data set that was used.
    out_dir : Path or None
        Where the artefacts were written.
    test_proba : ndarray
        P(error) of the kept decoder for the test epochs (in ``split.test`` order).
    candidates : dict of ErrPClassifier
        Every trained decoder by name (``eegnet``, ``lda``), the kept one included.
    """

    classifier: ErrPClassifier
    metrics: dict[str, Any]
    history: dict[str, list[float]]
    split: Split
    epochs: EpochSet
    out_dir: Path | None = None
    test_proba: np.ndarray = field(default_factory=lambda: np.empty(0))
    candidates: dict[str, ErrPClassifier] = field(default_factory=dict)


def stratified_split(
    y: np.ndarray, *, seed: int, fractions: tuple[float, float, float] = SPLIT_FRACTIONS
) -> Split:
    """Seeded split keeping the class ratio in every part.

    Per class, ``round(f_test * n_c)`` test and ``round(f_val * n_c)`` validation epochs
    are drawn at random; the rest is training data.
    """
    if not np.isclose(sum(fractions), 1.0):
        raise ValueError(f"split fractions must sum to 1, got {fractions}")
    rng = np.random.default_rng(seed)
    parts: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]] = ([], [], [])
    for cls in np.unique(y):
        idx = rng.permutation(np.flatnonzero(y == cls))
        n_test = round(fractions[2] * idx.size)
        n_val = round(fractions[1] * idx.size)
        parts[2].append(idx[:n_test])
        parts[1].append(idx[n_test : n_test + n_val])
        parts[0].append(idx[n_test + n_val :])
    train, val, test = (np.sort(np.concatenate(p)) for p in parts)
    return Split(train=train, val=val, test=test)


def roc_auc(y_true: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney U with tie correction); NaN for one class."""
    y_true = np.asarray(y_true).astype(bool)
    n_pos, n_neg = int(y_true.sum()), int((~y_true).sum())
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    order = np.argsort(score, kind="mergesort")
    ranks = np.empty(score.size)
    sorted_scores = np.asarray(score)[order]
    _, first, counts = np.unique(sorted_scores, return_index=True, return_counts=True)
    mean_ranks = first + (counts + 1) / 2.0  # 1-based average rank of each tie group
    ranks[order] = np.repeat(mean_ranks, counts)
    return float((ranks[y_true].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))


def classification_metrics(y_true: np.ndarray, proba: np.ndarray) -> dict[str, Any]:
    """Accuracy, balanced accuracy, ROC AUC and confusion matrix at threshold 0.5.

    The confusion matrix has rows = true class, columns = predicted class, in the order
    (correct, error).
    """
    y_true = np.asarray(y_true).astype(np.int64)
    y_pred = (np.asarray(proba) >= 0.5).astype(np.int64)
    cm = np.zeros((2, 2), dtype=np.int64)
    np.add.at(cm, (y_true, y_pred), 1)
    recalls = [cm[c, c] / cm[c].sum() for c in (0, 1) if cm[c].sum() > 0]
    return {
        "test_accuracy": float((y_true == y_pred).mean()) if y_true.size else float("nan"),
        "balanced_accuracy": float(np.mean(recalls)) if recalls else float("nan"),
        "roc_auc": roc_auc(y_true, np.asarray(proba)),
        "confusion_matrix": cm.tolist(),
    }


def _run_pass(
    model: EEGNet,
    X: torch.Tensor,
    y: torch.Tensor,
    loss_fn: nn.Module,
    *,
    optimizer: torch.optim.Optimizer | None = None,
    batch_size: int = 256,
    generator: torch.Generator | None = None,
) -> tuple[float, np.ndarray]:
    """One pass over (X, y); trains when ``optimizer`` is given. Returns (loss, P(error))."""
    training = optimizer is not None
    model.train(training)
    order = torch.randperm(len(y), generator=generator) if training else torch.arange(len(y))
    total, probas = 0.0, []
    with torch.set_grad_enabled(training):
        for start in range(0, len(y), batch_size):
            idx = order[start : start + batch_size]
            if training and idx.numel() < 2:
                continue  # batch norm needs more than one sample
            logits = model(X[idx])
            loss = loss_fn(logits, y[idx])
            if training:
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                model.apply_max_norm()
            total += float(loss.detach()) * idx.numel()
            probas.append(torch.softmax(logits.detach(), dim=1)[:, 1])
    proba = torch.cat(probas).numpy() if probas else np.empty(0)
    return total / max(1, len(y)), proba


def _new_model(
    n_chans: int, n_times: int, config: TrainingConfig, generator: torch.Generator
) -> EEGNet:
    """EEGNet initialised from ``generator`` (built on the meta device: no global draws)."""
    with torch.device("meta"):
        model = EEGNet(
            n_chans, 2, n_times, kernel_length=config.kernel_length, drop_prob=config.drop_prob
        )
    model = model.to_empty(device="cpu")
    model.reset_parameters(generator)
    return model


def _train_eegnet(
    epochs: EpochSet,
    split: Split,
    input_scale: float,
    *,
    seed: int,
    config: TrainingConfig,
    progress: bool,
    should_stop: Callable[[], bool] | None,
) -> tuple[EEGNet, dict[str, list[float]], dict[str, Any], np.ndarray, np.ndarray]:
    """EEGNet with early stopping on the validation loss.

    Returns the model (weights of the best pass), the history, its facts (``best_pass``,
    ``passes_run``, ``best_val_loss``) and P(error) on the validation and test epochs.
    """
    y_all = epochs.y
    # One stream for weights and dropout, one for minibatch order: what seeding torch's
    # global generator and a batch generator with ``seed`` gave, without global state.
    weights_rng = torch.Generator().manual_seed(seed)
    batch_rng = torch.Generator().manual_seed(seed)
    X = torch.from_numpy(np.ascontiguousarray(epochs.X * input_scale, dtype=np.float32))
    y = torch.from_numpy(y_all.astype(np.int64))
    n_chans, n_times = epochs.X.shape[1:]
    model = _new_model(n_chans, n_times, config, weights_rng)
    model.set_dropout_generator(weights_rng)
    counts = np.bincount(y_all[split.train], minlength=2).astype(np.float64)
    weights = torch.tensor(counts.sum() / (2.0 * np.maximum(counts, 1.0)), dtype=torch.float32)
    loss_fn = nn.CrossEntropyLoss(weight=weights)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    history: dict[str, list[float]] = {"train_loss": [], "val_loss": [], "val_accuracy": []}
    best_loss, best_pass, best_state = np.inf, -1, None
    passes = range(config.max_passes)
    if progress:
        from tqdm import tqdm

        passes = tqdm(passes, desc="training", unit="pass")
    Xtr, ytr = X[split.train], y[split.train]
    Xva, yva = X[split.val], y[split.val]
    try:
        for n_pass in passes:
            if should_stop is not None and should_stop():
                raise CalibrationCancelled(
                    f"calibration cancelled after {n_pass} of at most {config.max_passes} passes"
                )
            train_loss, _ = _run_pass(
                model,
                Xtr,
                ytr,
                loss_fn,
                optimizer=optimizer,
                batch_size=config.batch_size,
                generator=batch_rng,
            )
            val_loss, val_proba = _run_pass(model, Xva, yva, loss_fn)
            val_acc = float(((val_proba >= 0.5) == yva.numpy().astype(bool)).mean())
            history["train_loss"].append(train_loss)
            history["val_loss"].append(val_loss)
            history["val_accuracy"].append(val_acc)
            if val_loss < best_loss:
                best_loss, best_pass = val_loss, n_pass
                best_state = {k: v.clone() for k, v in model.state_dict().items()}
            elif n_pass - best_pass >= config.patience:
                break
    finally:
        model.set_dropout_generator(None)
        if progress:
            passes.close()
    assert best_state is not None
    model.load_state_dict(best_state)
    _, val_proba = _run_pass(model, Xva, yva, loss_fn)
    _, test_proba = _run_pass(model, X[split.test], y[split.test], loss_fn)
    facts = {
        "best_pass": int(best_pass),
        "passes_run": len(history["train_loss"]),
        "best_val_loss": float(best_loss),
    }
    return model, history, facts, val_proba, test_proba


def _decoder_metrics(
    epochs: EpochSet, split: Split, val_proba: np.ndarray, test_proba: np.ndarray, n_params: int
) -> dict[str, Any]:
    """Validation accuracies and test metrics of one decoder."""
    val = classification_metrics(epochs.y[split.val], val_proba)
    return {
        "val_accuracy": val["test_accuracy"],
        "val_balanced_accuracy": val["balanced_accuracy"],
        **classification_metrics(epochs.y[split.test], test_proba),
        "n_params": n_params,
    }


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

    EEGNet and the window-mean shrinkage LDA see the same training epochs (scaled by
    1 / their SD); the one with the higher validation accuracy is kept, EEGNet on a tie,
    and evaluated on the held-out test split.

    Parameters
    ----------
    epochs : EpochSet
        Labelled epochs (1 = error).
    seed : int
        Seeds the split, EEGNet's weight initialisation and minibatch order, and the LDA's
        cross-validation folds.
    config : TrainingConfig | None
        Hyperparameters and decoders; defaults to :class:`TrainingConfig`.
    split : Split | None
        Use these indices instead of :func:`stratified_split`.
    progress : bool
        Show a tqdm bar over training passes.
    should_stop : callable | None
        Called before every training pass and before the LDA fit; when it returns True,
        :class:`CalibrationCancelled` is raised.

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
    candidates: dict[str, ErrPClassifier] = {}
    decoders: dict[str, dict[str, Any]] = {}
    test_probas: dict[str, np.ndarray] = {}
    history: dict[str, list[float]] = {"train_loss": [], "val_loss": [], "val_accuracy": []}
    facts: dict[str, Any] = {}

    def bind(model: nn.Module) -> ErrPClassifier:
        return ErrPClassifier(
            model,
            epochs.params,
            epochs.ch_names,
            epochs.sfreq_in,
            input_scale,
            synthetic=epochs.synthetic,
        )

    if "eegnet" in config.decoders:
        model, history, facts, val_proba, test_proba = _train_eegnet(
            epochs,
            split,
            input_scale,
            seed=seed,
            config=config,
            progress=progress,
            should_stop=should_stop,
        )
        candidates["eegnet"] = bind(model)
        decoders["eegnet"] = _decoder_metrics(
            epochs, split, val_proba, test_proba, count_parameters(model)
        )
        test_probas["eegnet"] = test_proba
    if "lda" in config.decoders:
        if should_stop is not None and should_stop():
            raise CalibrationCancelled("calibration cancelled before the LDA fit")
        train_X = (epochs.X[split.train] * input_scale).astype(np.float32)
        fit = fit_window_lda(
            train_X, y_all[split.train], epochs.ch_names, epochs.params.sfreq_out, seed=seed
        )
        clf = bind(fit.model)
        candidates["lda"] = clf
        test_probas["lda"] = clf.predict_proba(epochs.X[split.test])
        decoders["lda"] = {
            **_decoder_metrics(
                epochs,
                split,
                clf.predict_proba(epochs.X[split.val]),
                test_probas["lda"],
                count_parameters(fit.model),
            ),
            "cv_folds": N_CV_FOLDS,
            "cv_accuracy_mean": float(np.mean(fit.cv_accuracy)),
            "cv_accuracy_std": float(np.std(fit.cv_accuracy)),
            "channels": fit.channels,
        }
    kept = max(decoders, key=lambda d: (decoders[d]["val_accuracy"], -DECODERS.index(d)))
    test_proba = test_probas[kept]
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
            **facts,
            "train_seconds": time.perf_counter() - t0,
            "seed": seed,
            "synthetic": epochs.synthetic,
            "training_config": asdict(config),
        }
    )
    classifier = candidates[kept]
    classifier.metrics = metrics
    return CalibrationResult(
        classifier=classifier,
        metrics=metrics,
        history=history,
        split=split,
        epochs=epochs,
        test_proba=test_proba,
        candidates=candidates,
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
        Also export ``model.onnx`` (a few seconds).
    progress : bool
        Show progress bars.
    should_stop : callable | None
        Polled before preprocessing and before every training pass (e.g. a job's cancel
        flag); True raises :class:`CalibrationCancelled`.

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
        result.out_dir = _write_outputs(result, Path(out_dir), report=report, onnx=onnx)
    return result


def _write_outputs(result: CalibrationResult, out: Path, *, report: bool, onnx: bool) -> Path:
    """Write the artefacts to a temporary sibling of ``out`` and move them in."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    try:
        result.classifier.save(staging)
        if onnx:
            result.classifier.export_onnx(staging)
        (staging / HISTORY_FILE).write_text(json.dumps(result.history))
        if report:
            from services.eeg.report import write_report

            write_report(result, staging)
        (staging / METRICS_FILE).write_text(json.dumps(result.metrics, indent=2))
        out.mkdir(exist_ok=True)
        names = sorted(p.name for p in staging.iterdir() if p.name != METRICS_FILE)
        # metrics.json marks a finished classifier: the old one goes first, and artefacts
        # of an earlier run that this run did not make (model.onnx, report) go too.
        (out / METRICS_FILE).unlink(missing_ok=True)
        for name in _ARTEFACTS - set(names):
            (out / name).unlink(missing_ok=True)
        for name in [*names, METRICS_FILE]:
            os.replace(staging / name, out / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out
