"""A recording with its ``Status`` stim channel replaced or added, read lazily.

MNE's readers give the EEG; the action markers become a ``Status`` channel (codes 1 correct,
2 error, as in the platform's BDF files). Building that channel must not copy the recording:
:class:`RawWithStatus` reads the source's samples a chunk at a time and adds one value per
sample, so a 600 MB upload stays a few hundred MB of memory (docs/eeg.md).
"""

from __future__ import annotations

import mne
import numpy as np

from services.eeg.recordings.conventions import STIM_CHANNEL


class RawWithStatus(mne.io.BaseRaw):
    """A recording read lazily with its ``Status`` channel replaced (or added) by ``status``.

    The other channels' samples are read from ``raw`` (lazily read or loaded) when asked
    for, a chunk at a time, exactly as ``raw`` gives them; ``Status`` is the last channel.
    So a Status channel made from annotations or BrainVision markers costs one value per
    sample, never a float64 copy of the whole recording.
    """

    def __init__(self, raw: mne.io.BaseRaw, status: np.ndarray) -> None:
        if status.shape != (raw.n_times,):
            raise ValueError(f"{status.shape[0]} Status values for {raw.n_times} samples")
        keep = [k for k, name in enumerate(raw.ch_names) if name != STIM_CHANNEL]
        info = mne.pick_info(raw.info, keep)
        stim = mne.create_info([STIM_CHANNEL], raw.info["sfreq"], ["stim"])["chs"][0]
        with info._unlock():
            info["chs"].append(stim)
            info._update_redundant()
        info._check_consistency()
        super().__init__(
            info,
            preload=False,
            first_samps=[raw.first_samp],
            last_samps=[raw.last_samp],
            filenames=[None],
            raw_extras=[{"source": raw, "picks": np.array(keep), "status": status}],
            orig_format="double",
            verbose="error",
        )
        # The source gives calibrated values (volts): read them as they are.
        self._cals = np.ones(info["nchan"])
        self.set_annotations(raw.annotations, verbose="error")

    def _read_segment_file(self, data, idx, fi, start, stop, cals, mult):
        """Fill ``data`` with channels ``idx`` of samples ``start:stop`` (MNE's reader API)."""
        extras = self._raw_extras[fi]
        source, picks, status = extras["source"], extras["picks"], extras["status"]
        wanted = np.arange(len(picks) + 1)[idx]
        block = np.empty((len(wanted), stop - start))
        from_source = wanted < len(picks)
        first = source.first_samp
        if from_source.any():
            block[from_source] = source.get_data(
                picks=picks[wanted[from_source]], start=start - first, stop=stop - first
            )
        block[~from_source] = status[start - first : stop - first]
        if mult is not None:
            data[:] = mult @ block
        else:
            np.multiply(block, cals, out=data, casting="unsafe")


def with_status(raw: mne.io.BaseRaw, status: np.ndarray) -> mne.io.BaseRaw:
    """``raw`` with ``status`` as its ``Status`` stim channel (replaced or added), read
    lazily (:class:`RawWithStatus`); a loaded ``raw`` gives a loaded result."""
    with_status = RawWithStatus(raw, np.asarray(status, dtype=np.float64))
    if raw.preload:
        with_status.load_data(verbose="error")
    return with_status
