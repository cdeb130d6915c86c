"""The seeded, stratified train / validation / test split every calibration decoder shares."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPLIT_FRACTIONS = (0.80, 0.12, 0.08)
"""Train / validation / test fractions (paper §EEG Classifier Training)."""


@dataclass
class Split:
    """Indices of the train, validation and test epochs."""

    train: np.ndarray
    val: np.ndarray
    test: np.ndarray


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
