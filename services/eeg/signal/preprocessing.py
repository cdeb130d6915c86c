"""ErrP preprocessing shared by calibration (offline) and live decoding (online).

One causal pipeline serves both paths, so a classifier trained on a recording sees exactly
the features it will see live (paper §EEG Classifier Training; docs/eeg.md):

1. down to ``sfreq_out``: when ``q = sfreq_in / sfreq_out`` is an integer (2048 Hz / 16 =
   128 Hz), an anti-alias low-pass at the input rate (Butterworth, ``antialias_order`` at
   ``antialias_cutoff`` Hz), then every ``q``-th sample; at any other rate (250, 500,
   1000 Hz...), rational resampling by ``up / down`` (``sfreq_out / sfreq_in`` in lowest
   terms, e.g. 64/125 at 250 Hz) with a causal polyphase FIR low-pass at
   ``antialias_cutoff`` Hz (Kaiser window, as :func:`scipy.signal.resample_poly`),
   computing only the output samples; its constant group delay is taken off the output
   timestamps, so an epoch covers the same stretch of signal at every rate;
2. band-pass ``l_freq``-``h_freq`` Hz at the output rate (Butterworth, ``filter_order``
   per band edge, as second-order sections);
3. a ring buffer of filtered samples with their timestamps, from which the epoch
   ``[tmin, tmax]`` s after an action onset is cut.

Every filter is causal and keeps its state across chunks, so feeding a recording in
pieces of any size gives the same samples as feeding it at once.
:func:`~services.eeg.recordings.epochs.epochs_from_raw` (calibration) runs the same
:class:`OnlinePreprocessor` over a recording in chunks, exactly as live ingest does.

Epoch length rule (MNE's): ``n_times_epoch = round(tmax * sfreq_out) - round(tmin *
sfreq_out) + 1``; both ends are included, so [0, 0.8] s at 128 Hz has 103 samples. An
epoch starts at the buffered sample nearest to ``onset + tmin`` (ties go to the later
sample).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from scipy import signal

from services.eeg.signal.filters import CausalPolyphase, CausalSosStage

_TIE_EPS_S = 1e-6
"""Tolerance (s) that makes sample selection at an exact tie independent of float rounding."""
MAX_RESAMPLING_FACTOR = 1000
"""Largest ``up`` or ``down`` of a rational resampling (250 Hz -> 128 Hz is 64/125)."""


class PreprocessingParams(BaseModel):
    """Parameters of the ErrP preprocessing (saved with every classifier).

    Attributes
    ----------
    l_freq, h_freq : float
        Band-pass edges in Hz (paper: 1-40 Hz).
    filter_order : int
        Butterworth order per band edge of the band-pass (the filter has ``2 *
        filter_order`` poles).
    sfreq_out : float
        Sampling rate of the features in Hz (paper: 128 Hz). The input rate may be any
        rate at least this high (see :meth:`resampling`).
    antialias_cutoff : float
        Cut-off in Hz of the anti-alias low-pass applied before resampling (-3 dB for the
        Butterworth, -6 dB for the FIR).
    antialias_order : int
        Butterworth order of the anti-alias low-pass (integer ratios).
    tmin, tmax : float
        Epoch window in s relative to the action onset (paper: [0, 0.8] s).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    l_freq: float = Field(1.0, gt=0)
    h_freq: float = Field(40.0, gt=0)
    filter_order: int = Field(2, ge=1, le=8)
    sfreq_out: float = Field(128.0, gt=0)
    antialias_cutoff: float = Field(48.0, gt=0)
    antialias_order: int = Field(8, ge=2, le=16)
    tmin: float = 0.0
    tmax: float = 0.8

    @model_validator(mode="after")
    def _check_consistent(self) -> PreprocessingParams:
        nyquist_out = self.sfreq_out / 2
        if not self.l_freq < self.h_freq < nyquist_out:
            raise ValueError(
                f"need l_freq < h_freq < sfreq_out / 2, got {self.l_freq}, {self.h_freq}, "
                f"{nyquist_out}"
            )
        if not self.h_freq <= self.antialias_cutoff < nyquist_out:
            raise ValueError(
                f"antialias_cutoff must lie in [h_freq, sfreq_out / 2), got {self.antialias_cutoff}"
            )
        if self.tmax <= self.tmin:
            raise ValueError(f"tmax ({self.tmax}) must be greater than tmin ({self.tmin})")
        return self

    @property
    def n_times_epoch(self) -> int:
        """Samples per epoch: ``round(tmax * sfreq_out) - round(tmin * sfreq_out) + 1``."""
        return round(self.tmax * self.sfreq_out) - round(self.tmin * self.sfreq_out) + 1

    def resampling(self, sfreq_in: float) -> tuple[int, int]:
        """``(up, down)`` in lowest terms with ``sfreq_in * up / down == sfreq_out``.

        ``ValueError`` if ``sfreq_in`` is below ``sfreq_out`` or not a ratio of integers
        up to :data:`MAX_RESAMPLING_FACTOR` (rates given to the millihertz).
        """
        if not math.isfinite(sfreq_in) or sfreq_in < self.sfreq_out - 1e-9:
            raise ValueError(
                f"sampling rate {sfreq_in} Hz is below the feature rate {self.sfreq_out} Hz"
            )
        ratio = Fraction(round(self.sfreq_out * 1000), round(sfreq_in * 1000))
        if ratio.denominator > MAX_RESAMPLING_FACTOR or not math.isclose(
            float(ratio) * sfreq_in, self.sfreq_out, rel_tol=1e-9
        ):
            raise ValueError(
                f"sampling rate {sfreq_in} Hz cannot be resampled to {self.sfreq_out} Hz by "
                f"a ratio of integers up to {MAX_RESAMPLING_FACTOR}"
            )
        return ratio.numerator, ratio.denominator

    def antialias_fir(self, sfreq_in: float) -> np.ndarray:
        """FIR taps of the rational resampler's low-pass at ``up * sfreq_in`` (gain ``up``).

        ``10 * max(up, down)`` taps each side of the centre and a Kaiser window (beta 5),
        as :func:`scipy.signal.resample_poly`, with the cut-off at ``antialias_cutoff``.
        """
        up, down = self.resampling(sfreq_in)
        half = 10 * max(up, down)
        taps = signal.firwin(
            2 * half + 1, self.antialias_cutoff, window=("kaiser", 5.0), fs=up * sfreq_in
        )
        return taps * up

    def antialias_sos(self, sfreq_in: float) -> np.ndarray:
        """Second-order sections of the anti-alias low-pass at the input rate."""
        return signal.butter(
            self.antialias_order, self.antialias_cutoff, btype="lowpass", fs=sfreq_in, output="sos"
        )

    def bandpass_sos(self) -> np.ndarray:
        """Second-order sections of the band-pass at the output rate."""
        return signal.butter(
            self.filter_order,
            [self.l_freq, self.h_freq],
            btype="bandpass",
            fs=self.sfreq_out,
            output="sos",
        )


class EpochUnavailableError(LookupError):
    """The requested epoch starts before the oldest sample still buffered."""


class OnlinePreprocessor:
    """Causal filter, resampler and timestamped ring buffer for one EEG stream.

    Parameters
    ----------
    ch_names : sequence of str
        Channel names, in the column order of the samples passed to :meth:`push`.
    sfreq_in : float
        Sampling rate of the incoming samples in Hz (at least ``params.sfreq_out``).
    params : PreprocessingParams | None
        Filter and epoch parameters; defaults to the paper's.
    buffer_s : float
        Seconds of filtered data kept for :meth:`epoch_at`.

    Notes
    -----
    Timestamps of the samples in a chunk are ``first_timestamp + i / sfreq_in``. Call
    :meth:`reset` after a discontinuity (gap, clock jump, reconnect): the filter restarts
    from the next sample and the buffer is emptied, so no epoch spans the break.
    """

    def __init__(
        self,
        ch_names: Sequence[str],
        sfreq_in: float,
        params: PreprocessingParams | None = None,
        *,
        buffer_s: float = 30.0,
    ) -> None:
        self.params = params or PreprocessingParams()
        self.ch_names = list(ch_names)
        if not self.ch_names:
            raise ValueError("no channels given")
        if len(set(self.ch_names)) != len(self.ch_names):
            raise ValueError("channel names must be unique")
        self.sfreq_in = float(sfreq_in)
        self.up, self.down = self.params.resampling(self.sfreq_in)
        if buffer_s <= self.params.tmax - self.params.tmin:
            raise ValueError(f"buffer_s ({buffer_s}) must exceed the epoch length")
        self._capacity = math.ceil(buffer_s * self.params.sfreq_out)
        n_ch = len(self.ch_names)
        self._antialias: CausalSosStage | None = None
        self._resampler: CausalPolyphase | None = None
        if self.up == 1:  # integer ratio: Butterworth and every ``down``-th sample
            self._antialias = CausalSosStage(self.params.antialias_sos(self.sfreq_in))
        else:
            taps = self.params.antialias_fir(self.sfreq_in)
            self._resampler = CausalPolyphase(taps, self.up, self.down)
        self._bandpass = CausalSosStage(self.params.bandpass_sos())
        self._data = np.empty((n_ch, 2 * self._capacity))
        self._times = np.empty(2 * self._capacity)
        self._n_in = 0
        self._start = 0
        self._stop = 0

    @property
    def n_channels(self) -> int:
        return len(self.ch_names)

    @property
    def n_times_epoch(self) -> int:
        return self.params.n_times_epoch

    @property
    def n_buffered(self) -> int:
        """Number of filtered output samples in the buffer."""
        return self._stop - self._start

    @property
    def latest_timestamp(self) -> float | None:
        """Timestamp of the newest buffered output sample (None if empty)."""
        return float(self._times[self._stop - 1]) if self.n_buffered else None

    @property
    def oldest_timestamp(self) -> float | None:
        """Timestamp of the oldest buffered output sample (None if empty)."""
        return float(self._times[self._start]) if self.n_buffered else None

    def reset(self) -> None:
        """Forget filter state and buffered data (after a discontinuity in the stream)."""
        if self._antialias is not None:
            self._antialias.reset()
        if self._resampler is not None:
            self._resampler.reset()
        self._bandpass.reset()
        self._n_in = 0
        self._start = self._stop = 0

    def push(self, samples: np.ndarray, first_timestamp: float) -> None:
        """Filter a chunk of samples and append the resampled result to the buffer.

        Parameters
        ----------
        samples : ndarray, shape (n_times, n_channels)
            EEG in volts, columns in ``ch_names`` order.
        first_timestamp : float
            Time (s) of ``samples[0]`` on the stream's clock.
        """
        samples = np.asarray(samples)
        if samples.ndim != 2 or samples.shape[1] != self.n_channels:
            raise ValueError(
                f"expected samples of shape (n_times, {self.n_channels}), got {samples.shape}"
            )
        n = samples.shape[0]
        if n == 0:
            return
        x = np.ascontiguousarray(samples.T, dtype=np.float64)
        if not np.all(np.isfinite(x)):
            raise ValueError("samples contain NaN or infinite values")
        if self._resampler is not None:
            y, positions = self._resampler(x)
            positions = positions - self._resampler.delay_in
        else:
            assert self._antialias is not None
            offset = (-self._n_in) % self.down
            y = np.ascontiguousarray(self._antialias(x)[:, offset :: self.down])
            positions = offset + self.down * np.arange(y.shape[1])
        self._n_in += n
        if y.shape[1] == 0:
            return
        z = self._bandpass(y)
        self._append(z, first_timestamp + positions / self.sfreq_in)

    def _append(self, z: np.ndarray, times: np.ndarray) -> None:
        k = z.shape[1]
        if k >= self._capacity:
            z, times, k = z[:, -self._capacity :], times[-self._capacity :], self._capacity
        if self._stop + k > self._data.shape[1]:
            keep = min(self.n_buffered, self._capacity - k)
            self._data[:, :keep] = self._data[:, self._stop - keep : self._stop]
            self._times[:keep] = self._times[self._stop - keep : self._stop]
            self._start, self._stop = 0, keep
        self._data[:, self._stop : self._stop + k] = z
        self._times[self._stop : self._stop + k] = times
        self._stop += k
        self._start = max(self._start, self._stop - self._capacity)

    def epoch_at(self, onset: float) -> np.ndarray | None:
        """The preprocessed epoch ``[tmin, tmax]`` s after ``onset``.

        Parameters
        ----------
        onset : float
            Action onset on the stream's clock (s).

        Returns
        -------
        ndarray, shape (n_channels, n_times_epoch), float32, or None
            The epoch in volts; None while the window is not yet complete.

        Raises
        ------
        EpochUnavailableError
            If the window starts before the oldest buffered sample (expired or before the
            stream started).
        """
        p = self.params
        if self.n_buffered == 0:
            return None
        times = self._times[self._start : self._stop]
        target = onset + p.tmin
        half = 0.5 / p.sfreq_out
        if target < times[0] - half - _TIE_EPS_S:
            raise EpochUnavailableError(
                f"epoch at {onset:.3f} s starts before the oldest buffered sample "
                f"({times[0]:.3f} s)"
            )
        i = int(np.searchsorted(times, target - half + _TIE_EPS_S, side="left"))
        n = p.n_times_epoch
        if i + n > times.size:
            return None
        return self._data[:, self._start + i : self._start + i + n].astype(np.float32)
