"""A recording's labelled epochs: its action events cut from the online preprocessing.

:func:`epochs_from_raw` runs the live path's
:class:`~services.eeg.signal.preprocessing.OnlinePreprocessor` over a recording in chunks
and cuts the epoch after every action of its ``Status`` channel, so a classifier is
calibrated on exactly the features it sees live.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mne
import numpy as np

from services.core.actions import TRIGGER_ERROR
from services.eeg.recordings.io import action_events, is_synthetic
from services.eeg.signal.preprocessing import OnlinePreprocessor, PreprocessingParams


@dataclass(frozen=True)
class EpochSet:
    """Labelled ErrP epochs ready for the classifier.

    Attributes
    ----------
    X : ndarray, shape (n_epochs, n_channels, n_times_epoch), float32
        Preprocessed epochs in volts.
    y : ndarray, shape (n_epochs,), int64
        1 = error (trigger code 2), 0 = correct (trigger code 1).
    ch_names : list of str
        Channel order of ``X``.
    params : PreprocessingParams
        Preprocessing that produced ``X``.
    sfreq_in : float
        Sampling rate (Hz) of the recording before preprocessing.
    synthetic : bool
        True when the recording came from the virtual subject.
    """

    X: np.ndarray
    y: np.ndarray
    ch_names: list[str]
    params: PreprocessingParams
    sfreq_in: float
    synthetic: bool = False

    def __post_init__(self) -> None:
        if self.X.ndim != 3 or self.X.shape[0] != self.y.shape[0]:
            raise ValueError(f"X {self.X.shape} and y {self.y.shape} do not match")
        if self.X.shape[1] != len(self.ch_names):
            raise ValueError(f"X has {self.X.shape[1]} channels, ch_names {len(self.ch_names)}")

    def __len__(self) -> int:
        return int(self.y.shape[0])


def epochs_from_raw(
    raw: mne.io.BaseRaw,
    params: PreprocessingParams | None = None,
    *,
    picks: str | Sequence[str] = "eeg",
    chunk_s: float = 4.0,
    progress: bool = False,
) -> EpochSet:
    """Preprocess a recording with :class:`OnlinePreprocessor` and cut labelled epochs.

    Parameters
    ----------
    raw : mne.io.BaseRaw
        Preloaded recording with a ``Status`` trigger channel (codes 1 correct, 2 error).
    params : PreprocessingParams | None
        Defaults to the paper's parameters.
    picks : str | sequence of str
        Channels to use (MNE picks), default all EEG channels.
    chunk_s : float
        Seconds fed to the preprocessor per push (any value gives the same epochs).
    progress : bool
        Show a tqdm progress bar over the recording.

    Returns
    -------
    EpochSet
        Epochs whose window lies fully inside the recording, in onset order.
    """
    params = params or PreprocessingParams()
    pick_idx = _pick_indices(raw, picks)
    ch_names = [raw.ch_names[i] for i in pick_idx]
    sfreq = float(raw.info["sfreq"])
    events = action_events(raw)
    if len(events) == 0:
        raise ValueError("recording has no action events in its Status channel")
    onsets = (events[:, 0] - raw.first_samp) / sfreq
    labels = (events[:, 2] == TRIGGER_ERROR).astype(np.int64)
    pre = OnlinePreprocessor(ch_names, sfreq, params, buffer_s=max(30.0, 4 * chunk_s))
    chunk = max(1, round(chunk_s * sfreq))
    X = np.empty((len(events), len(ch_names), params.n_times_epoch), dtype=np.float32)
    done = np.zeros(len(events), dtype=bool)
    next_event = 0
    starts = range(0, raw.n_times, chunk)
    if progress:
        from tqdm import tqdm

        starts = tqdm(starts, desc="preprocessing", unit="chunk")
    for start in starts:
        stop = min(start + chunk, raw.n_times)
        data = raw.get_data(picks=pick_idx, start=start, stop=stop)
        pre.push(data.T, start / sfreq)
        while next_event < len(events):
            epoch = pre.epoch_at(float(onsets[next_event]))
            if epoch is None:
                break
            X[next_event] = epoch
            done[next_event] = True
            next_event += 1
    return EpochSet(
        X=X[done],
        y=labels[done],
        ch_names=ch_names,
        params=params,
        sfreq_in=sfreq,
        synthetic=is_synthetic(raw),
    )


def _pick_indices(raw: mne.io.BaseRaw, picks: str | Sequence[str]) -> np.ndarray:
    """Channel indices for ``picks`` ("eeg" or channel names); ``ValueError`` if none."""
    if isinstance(picks, str) and picks == "eeg":
        idx = mne.pick_types(raw.info, eeg=True, exclude="bads")
    else:
        names = [picks] if isinstance(picks, str) else list(picks)
        missing = sorted(set(names) - set(raw.ch_names))
        if missing:
            raise ValueError(f"channels not in the recording: {missing}")
        idx = mne.pick_channels(raw.ch_names, include=names, ordered=True)
    if len(idx) == 0:
        raise ValueError(f"no channels match picks={picks!r}")
    return np.asarray(idx)
