"""Labelled test epochs with a known pattern (test helper; not EEG)."""

from __future__ import annotations

import numpy as np

from services.eeg.recordings.epochs import EpochSet
from services.eeg.signal.preprocessing import PreprocessingParams
from services.eeg.virtual.subject import eeg_channel_names

CH_NAMES = eeg_channel_names()
"""The virtual subject's 64 channels, the order of the epochs' rows."""


def patterned_epochs(channels: list[str], n: int = 200, seed: int = 0) -> EpochSet:
    """Test data (not EEG): white noise plus a fixed deflection on ``channels`` at 200-400
    ms in error epochs (about 40 % of ``n``)."""
    rng = np.random.default_rng(seed)
    y = (rng.random(n) < 0.4).astype(np.int64)
    X = rng.normal(scale=10e-6, size=(n, 64, 103)).astype(np.float32)
    rows = [CH_NAMES.index(c) for c in channels]
    X[np.ix_(y == 1, rows, range(26, 51))] += 4e-6
    return EpochSet(X, y, CH_NAMES, PreprocessingParams(), 2048.0, synthetic=True)
