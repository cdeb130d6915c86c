"""Causal filters whose state persists across chunks (used by services.eeg.signal.preprocessing).

Feeding a signal to either in pieces of any size gives the same samples as feeding it at
once, which is what makes offline (calibration) and online (live) preprocessing equal.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

__all__ = ["CausalPolyphase", "CausalSosStage"]


class CausalSosStage:
    """A causal SOS filter over channels whose state persists across chunks.

    The state is initialised from the first sample (steady state for a constant input),
    so a DC offset at the start of a stream causes no step response.
    """

    def __init__(self, sos: np.ndarray) -> None:
        self.sos = sos
        self._zi_unit = signal.sosfilt_zi(sos)  # (n_sections, 2)
        self._zi: np.ndarray | None = None

    def reset(self) -> None:
        self._zi = None

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter ``x`` of shape (n_channels, n_times) along time."""
        if x.shape[1] == 0:
            return x
        if self._zi is None:
            self._zi = self._zi_unit[:, None, :] * x[None, :, 0, None]
        y, self._zi = signal.sosfilt(self.sos, x, axis=1, zi=self._zi)
        return y


class CausalPolyphase:
    """Causal rational resampler by ``up / down`` (polyphase FIR) over channels.

    Output sample ``m`` is ``sum_j h[j] * xup[m * down - j]`` where ``xup`` is the input
    with ``up - 1`` zeros after every sample; only the non-zero products are computed.
    The input before the first sample is taken as that sample (no step response), and
    the state (the last input samples and the count) persists across chunks.
    """

    def __init__(self, taps: np.ndarray, up: int, down: int) -> None:
        self.up, self.down = up, down
        self.n_phase_taps = math.ceil(taps.size / up)
        padded = np.zeros(self.n_phase_taps * up)
        padded[: taps.size] = taps
        # phases[p, i] = h[p + up * i]; reversed so a window of inputs in time order dots it
        self._phases = padded.reshape(self.n_phase_taps, up).T[:, ::-1].copy()
        self.delay_in = (taps.size - 1) / 2 / up
        """Group delay in input samples."""
        self._history: np.ndarray | None = None
        self._n_in = 0
        self._n_out = 0

    def reset(self) -> None:
        self._history = None
        self._n_in = self._n_out = 0

    def __call__(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Resample ``x`` (n_channels, n_times); returns the new output samples and, for
        each, its position in input samples relative to ``x[:, 0]`` (fractional)."""
        n = x.shape[1]
        if n == 0:
            return x[:, :0], np.empty(0)
        if self._history is None:
            self._history = np.repeat(x[:, :1], self.n_phase_taps - 1, axis=1)
        joined = np.concatenate([self._history, x], axis=1)
        first_in = self._n_in
        self._n_in += n
        # output m needs input floor(m * down / up); all with that index below _n_in
        stop = -(-self._n_in * self.up // self.down)
        m = np.arange(self._n_out, stop)
        self._n_out = stop
        self._history = joined[:, joined.shape[1] - (self.n_phase_taps - 1) :]
        if m.size == 0:
            return x[:, :0], np.empty(0)
        k = m * self.down
        last = k // self.up - first_in + self.n_phase_taps - 1  # index in ``joined``
        windows = np.lib.stride_tricks.sliding_window_view(joined, self.n_phase_taps, axis=1)
        picked = windows[:, last - (self.n_phase_taps - 1)]  # (n_ch, n_out, n_phase_taps)
        y = np.einsum("cmt,mt->cm", picked, self._phases[k % self.up])
        return y, k / self.up - first_in
