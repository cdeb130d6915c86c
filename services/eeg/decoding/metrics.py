"""Held-out metrics of an ErrP decoder: accuracy, balanced accuracy, ROC AUC, confusion."""

from __future__ import annotations

from typing import Any

import numpy as np


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


def validation_and_test_metrics(
    y_val: np.ndarray, val_proba: np.ndarray, y_test: np.ndarray, test_proba: np.ndarray
) -> dict[str, Any]:
    """A decoder's validation accuracies (what selection compares) and its test metrics."""
    val = classification_metrics(y_val, val_proba)
    return {
        "val_accuracy": val["test_accuracy"],
        "val_balanced_accuracy": val["balanced_accuracy"],
        **classification_metrics(y_test, test_proba),
    }
