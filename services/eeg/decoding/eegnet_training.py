"""EEGNet's calibration training (the paper's recipe) on one split.

Class-weighted cross-entropy (errors are the minority class); Adam; early stopping on the
validation loss (the weights of the best training pass are kept). All randomness comes
from local generators seeded with ``seed`` (``torch.Generator`` for weights, dropout and
minibatch order), so neither torch's global generator nor its thread count is touched;
the results equal those of seeding the global generator with ``seed``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from services.eeg.decoding.eegnet import EEGNet
from services.eeg.decoding.split import Split
from services.eeg.decoding.training_config import CalibrationCancelled, TrainingConfig
from services.eeg.recordings.epochs import EpochSet


@dataclass
class EEGNetFit:
    """A trained EEGNet, its per-pass history and P(error) on validation and test."""

    model: EEGNet
    history: dict[str, list[float]]
    """Per-pass ``train_loss``, ``val_loss``, ``val_accuracy``."""
    facts: dict[str, Any]
    """``best_pass``, ``passes_run``, ``best_val_loss``."""
    val_proba: np.ndarray
    test_proba: np.ndarray


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


def train_eegnet(
    epochs: EpochSet,
    split: Split,
    input_scale: float,
    *,
    seed: int,
    config: TrainingConfig,
    progress: bool = False,
    should_stop: Callable[[], bool] | None = None,
) -> EEGNetFit:
    """EEGNet on ``split.train`` with early stopping on ``split.val``.

    ``should_stop`` is polled before every pass; True raises :class:`CalibrationCancelled`.
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
    return EEGNetFit(model, history, facts, val_proba, test_proba)
