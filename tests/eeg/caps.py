"""SYNTHETIC virtual-subject recordings on other caps and rates (test helper).

The virtual subject simulates the 64-channel BioSemi cap, whose names are 10-10 positions:
the 8- and 32-channel caps below are subsets of it (standard_1020 / standard_1005 names).
Rates the generator does not make itself (below 256 Hz) are made from a 1000 Hz
simulation with scipy's resample_poly (offline, zero-phase: test data only) and the
action pulses placed on the nearest sample.
"""

from __future__ import annotations

from fractions import Fraction

import mne
import numpy as np
from scipy import signal

from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.virtual.subject import simulate_recording

CAP_8 = ["Fz", "FC1", "FCz", "FC2", "C3", "Cz", "C4", "Pz"]
"""A small ErrP cap (10-10 names)."""
CAP_32 = list(mne.channels.make_standard_montage("biosemi32").ch_names)
"""BioSemi's 32-channel cap (10-20 names, FCz absent: FC1/FC2 carry the site)."""
CAP_64 = list(mne.channels.make_standard_montage("biosemi64").ch_names)
LABELS = [True, False, True, True, False, True, False, True, True, False]


def virtual_recording(
    sfreq: float,
    channels: list[str],
    *,
    labels: list[bool] = LABELS,
    quality: float = 1.0,
    seed: int = 0,
) -> mne.io.RawArray:
    """A short synthetic recording with ``channels`` and a ``Status`` channel at ``sfreq``."""
    base = sfreq if sfreq >= 256 else 1000.0
    raw = simulate_recording(labels, quality=quality, seed=seed, sfreq=base)
    raw.pick([*channels, STIM_CHANNEL])
    if base == sfreq:
        return raw
    ratio = Fraction(round(sfreq), round(base))
    eeg = signal.resample_poly(
        raw.get_data(picks=channels), ratio.numerator, ratio.denominator, axis=1
    )
    stim = raw.get_data(picks=[STIM_CHANNEL])[0]
    onsets = np.flatnonzero(np.diff(stim, prepend=0) > 0)
    status = np.zeros(eeg.shape[1])
    status[np.round(onsets * float(ratio)).astype(int)] = stim[onsets]
    info = mne.create_info([*channels, STIM_CHANNEL], sfreq, ["eeg"] * len(channels) + ["stim"])
    info["description"] = raw.info["description"]
    out = mne.io.RawArray(np.vstack([eeg, status[None]]), info, verbose="error")
    return out
