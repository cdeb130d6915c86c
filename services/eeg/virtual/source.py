"""The virtual subject as a live, **synthetic** EEG source driven by action markers.

:class:`VirtualEEGSource` generates the virtual subject's EEG (the model of
:mod:`services.eeg.virtual.subject`: the same ErrP, correct-trial and visual components with
their per-trial jitter, the same background, artefacts and noise, the same ``quality`` knob)
continuously, on its own clock, sample by sample as far as it is asked to. Each executed
action is fed in with :meth:`VirtualEEGSource.add_marker`: the subject then responds to it
as the offline generator responds to a labelled action (an ErrP after an error, i.e. a marker
whose oracle label ``correct`` is False, the weaker bump after a correct one, the visual
response after every action) and its ``Status`` channel carries the marker's trigger code.

With the same ``seed`` the subject is the offline subject (same latency shift and ErrP
topographies); the background is a new realisation of the same model, drawn in 20 s
segments cross-faded over 1 s (equal power), so it never ends. The samples depend only on the
seed and the markers, not on how generation is chunked.

Two drivers feed the source to the EEG service:

* :class:`services.eeg.virtual.ingest.VirtualIngestClient` (accelerated): no wall-clock
  pacing; generated samples are pushed with their timestamps to ``WS /live/ingest`` up to
  each marker's epoch end, so a session runs as fast as compute allows through the live
  decoding path.
* :class:`services.eeg.virtual.stream.VirtualLslStream` (real time): an LSL outlet pushed
  at wall-clock pace, following the sim's marker stream (``bgrl subject stream``).

Everything is marked synthetic: :attr:`VirtualEEGSource.description` starts with
``"SYNTHETIC"``, the ingest header says ``synthetic: true`` and the LSL stream's description
carries it.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import signal

from services.core.markers import ActionMarker
from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_TAG, TRIGGER_PULSE_S
from services.eeg.virtual.subject import (
    ALPHA_RMS_UV,
    BLINK_PEAK_UV,
    BRAIN_RMS_UV,
    CORRECT_COMPONENTS,
    DRIFT_RMS_UV,
    ERP_WINDOW_S,
    ERROR_COMPONENTS,
    ERRP_GAIN,
    LINE_FREQ_HZ,
    LINE_RMS_UV,
    LOCAL_NOISE_CORNER_HZ,
    LOCAL_NOISE_UV,
    MAX_SUBJECT_SHIFT_S,
    MIN_SFREQ,
    N_BRAIN_SOURCES,
    N_DRIFT_SOURCES,
    SENSOR_NOISE_UV,
    VISUAL_COMPONENTS,
    ErpComponent,
    VirtualSubject,
    blink_train,
    colored_noise,
    component_waveforms,
    electrode_positions,
    line_source,
    topography,
)

logger = logging.getLogger(__name__)

SEGMENT_S = 20.0
"""Length of one background realisation (s)."""
CROSSFADE_S = 1.0
"""Overlap over which consecutive background realisations are cross-faded (s)."""
DEFAULT_SFREQ = 256.0
"""Default rate: the lowest the model supports, the cheapest to ship over the ingest."""

_STREAM_BACKGROUND, _STREAM_BLINKS, _STREAM_NOISE, _STREAM_TRIALS = 1, 2, 3, 4
"""Independent random streams below the subject's seed (``default_rng([seed, stream, k])``)."""


@dataclass(frozen=True)
class _Response:
    """One action's evoked response and trigger, in samples of the source."""

    onset: int
    evoked: np.ndarray  # (n_channels, n_window) float32, volts
    code: int


class VirtualEEGSource:
    """The virtual subject's EEG, generated continuously on a virtual clock.

    Parameters
    ----------
    quality : float
        ErrP strength in [0, 1] (as :class:`~services.eeg.virtual.subject.VirtualSubject`).
    seed : int
        Seed of the subject and of every random draw.
    sfreq : float
        Sampling rate (Hz), at least 256.
    channels : sequence of str | None
        EEG channels to produce, in order (BioSemi 64 names; default all 64). ``Status`` is
        always appended as the last column.
    latency_shift_s : float | None
        The subject's ErrP latency shift (s, within +-0.1); drawn from ``seed`` when None,
        as the offline generator does.
    start_timestamp : float
        Timestamp of the first sample (the LSL clock in real time, any origin otherwise).
    session : int
        Which recording session of the subject: the same subject (latency shift, ErrP and
        background topographies, alpha peak, line-noise gains) in a new realisation of its
        background, blinks, channel noise and per-trial jitter. Session 0 is the default
        source's; the end-to-end feedback source calibrates on one session and decodes
        another (``services.worker.e2e_feedback``).

    Sample ``i`` has timestamp ``start_timestamp + i / sfreq``. Thread-safe: markers may be
    added from another thread while samples are generated.
    """

    def __init__(
        self,
        *,
        quality: float,
        seed: int,
        sfreq: float = DEFAULT_SFREQ,
        channels: Sequence[str] | None = None,
        latency_shift_s: float | None = None,
        start_timestamp: float = 0.0,
        session: int = 0,
    ) -> None:
        subject = VirtualSubject(quality=quality, seed=seed, latency_shift_s=latency_shift_s)
        if session < 0:
            raise ValueError(f"session must be >= 0, got {session}")
        if not math.isfinite(sfreq) or sfreq < MIN_SFREQ:
            raise ValueError(f"sfreq must be a finite rate >= {MIN_SFREQ} Hz, got {sfreq}")
        if not math.isfinite(start_timestamp):
            raise ValueError(f"start_timestamp must be finite, got {start_timestamp}")
        names, positions = electrode_positions()
        index = {name: i for i, name in enumerate(names)}
        wanted = list(names) if channels is None else list(channels)
        unknown = [ch for ch in wanted if ch not in index]
        if unknown or not wanted or len(set(wanted)) != len(wanted):
            raise ValueError(
                f"channels must be distinct BioSemi 64 names, got unknown {unknown}"
                if unknown
                else "channels must be a non-empty list of distinct names"
            )
        rows = np.array([index[ch] for ch in wanted])
        self.quality = subject.quality
        self.seed = seed
        self.session = int(session)
        self.sfreq = float(sfreq)
        self.start_timestamp = float(start_timestamp)
        self.eeg_ch_names = wanted
        self.ch_names = [*wanted, STIM_CHANNEL]

        # The subject: drawn in the offline generator's order (shift, then topography jitter).
        rng = np.random.default_rng(seed)
        shift = float(rng.uniform(-MAX_SUBJECT_SHIFT_S, MAX_SUBJECT_SHIFT_S))
        self.latency_shift_s = shift if subject.latency_shift_s is None else subject.latency_shift_s
        topo_jitter = rng.normal(0.0, 0.008, size=(3, 3))
        gain = subject.quality * ERRP_GAIN

        def group_patterns(components: Sequence[ErpComponent], g: int, scale: float):
            return np.array(
                [
                    scale
                    * c.amplitude_uv
                    * 1e-6
                    * topography(positions, positions[index[c.centre]] + topo_jitter[g], c.spread_m)
                    for c in components
                ]
            )[:, rows]

        self._groups = {
            "error": (ERROR_COMPONENTS, group_patterns(ERROR_COMPONENTS, 0, gain)),
            "correct": (CORRECT_COMPONENTS, group_patterns(CORRECT_COMPONENTS, 1, gain)),
            "visual": (VISUAL_COMPONENTS, group_patterns(VISUAL_COMPONENTS, 2, 1.0)),
        }
        self._window = np.arange(round(ERP_WINDOW_S * self.sfreq)) / self.sfreq

        # Background patterns (spatially smooth brain sources, alpha, drift), then the
        # blink, line-noise and channel-noise parameters: all fixed for the subject.
        n_all = len(names)
        brain = np.empty((N_BRAIN_SOURCES, n_all))
        for k in range(N_BRAIN_SOURCES):
            centre = positions[rng.integers(n_all)] * rng.uniform(0.6, 1.0)
            brain[k] = rng.choice([-1.0, 1.0]) * topography(
                positions, centre, rng.uniform(0.03, 0.07)
            )
        brain *= BRAIN_RMS_UV * 1e-6 / np.sqrt(np.mean(np.sum(brain**2, axis=0)))
        self._alpha_peak = float(rng.uniform(9.0, 11.0))
        alpha = ALPHA_RMS_UV * 1e-6 * topography(positions, positions[index["Oz"]], 0.05)
        drift = DRIFT_RMS_UV * 1e-6 * rng.normal(0, 1, (N_DRIFT_SOURCES, n_all)) / 2.0
        self._background_mixing = np.vstack([brain, alpha[None], drift])[:, rows].T.astype(
            np.float32
        )
        eye = np.array([0.0, 0.11, -0.02])
        self._blink_pattern = (BLINK_PEAK_UV * 1e-6 * topography(positions, eye, 0.045))[
            rows
        ].astype(np.float32)
        self._line: list[tuple[np.ndarray, Any]] = []
        for freq, rel in ((LINE_FREQ_HZ, 1.0), (2 * LINE_FREQ_HZ, 0.25)):
            for trig in (np.sin, np.cos):
                pattern = rel * LINE_RMS_UV * 1e-6 * rng.uniform(0.2, 1.0, n_all)
                self._line.append(
                    (pattern[rows].astype(np.float32), line_source(trig, freq, self.sfreq))
                )
        pole = math.exp(-2.0 * math.pi * LOCAL_NOISE_CORNER_HZ / self.sfreq)
        local_gain = LOCAL_NOISE_UV * 1e-6 * math.sqrt(1.0 - pole**2) / (1.0 - pole)
        sensor = SENSOR_NOISE_UV * 1e-6
        self._noise_b = np.array([(1.0 - pole) * local_gain + sensor, -pole * sensor])
        self._noise_a = np.array([1.0, -pole])
        self._noise_state = (rng.standard_normal((n_all, 1))[rows] * LOCAL_NOISE_UV * 1e-6).astype(
            np.float32
        )
        self._noise_rng = self._stream(_STREAM_NOISE)

        self._segment = round(SEGMENT_S * self.sfreq)
        self._fade = round(CROSSFADE_S * self.sfreq)
        self._segments: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._responses: list[_Response] = []
        self._pulse = max(1, round(TRIGGER_PULSE_S * self.sfreq))
        self._lock = threading.Lock()
        self.n_generated = 0
        self.n_markers = 0
        self.late_markers = 0
        self.description = (
            f"{SYNTHETIC_TAG} virtual subject live quality={self.quality:g} seed={seed} "
            f"shift={self.latency_shift_s:+.3f}s"
        )

    def _stream(self, *keys: int) -> np.random.Generator:
        """The random stream ``keys`` of this subject's session (session 0: the seed and
        the keys alone, as before sessions existed)."""
        session = [self.session] if self.session else []
        return np.random.default_rng([self.seed, *keys, *session])

    # ------------------------------------------------------------------ clock
    @property
    def synthetic(self) -> bool:
        """Always True: the data are generated, not recorded."""
        return True

    @property
    def next_timestamp(self) -> float:
        """Timestamp of the next sample to be generated."""
        return self.start_timestamp + self.n_generated / self.sfreq

    def sample_at(self, timestamp: float) -> int:
        """Index of the sample nearest to ``timestamp`` on this source's clock."""
        return round((timestamp - self.start_timestamp) * self.sfreq)

    # ---------------------------------------------------------------- markers
    def add_marker(self, marker: ActionMarker) -> None:
        """Make the subject watch the action of ``marker`` (at ``marker.timestamp``).

        ``marker.correct`` False: the ErrP; True: the correct-trial bump; None: the visual
        response only. The ``Status`` channel gets the marker's trigger code. Feed markers
        before generating past their onset: the part of a response whose samples were
        already generated is lost (counted in :attr:`late_markers`).
        """
        with self._lock:
            rng = self._stream(_STREAM_TRIALS, self.n_markers)
            self.n_markers += 1
            onset = self.sample_at(marker.timestamp)
            evoked = np.zeros((len(self.eeg_ch_names), self._window.size), dtype=np.float64)
            groups = ["visual"]
            if marker.correct is not None:
                groups.insert(0, "correct" if marker.correct else "error")
            for name in groups:
                components, patterns = self._groups[name]
                waves = component_waveforms(components, 1, self._window, self.latency_shift_s, rng)[
                    :, 0
                ]
                evoked += patterns.T @ waves
            if onset < self.n_generated:
                self.late_markers += 1
                logger.warning(
                    "marker %s:%d arrived %.3f s after its onset was generated; "
                    "its response is cut",
                    marker.session_id,
                    marker.step,
                    (self.n_generated - onset) / self.sfreq,
                )
            self._responses.append(_Response(onset, evoked.astype(np.float32), marker.trigger))

    # ------------------------------------------------------------- generation
    def generate_until(self, timestamp: float) -> tuple[np.ndarray, float]:
        """Generate every sample before ``timestamp`` not generated yet.

        Returns
        -------
        samples : ndarray, shape (n_times, n_channels), float32
            EEG in volts, ``Status`` codes in the last column; ``n_times`` may be 0.
        first_timestamp : float
            Timestamp of ``samples[0]`` (the next sample's when empty).
        """
        with self._lock:
            start = self.n_generated
            stop = max(start, math.ceil((timestamp - self.start_timestamp) * self.sfreq - 1e-9))
            first = self.start_timestamp + start / self.sfreq
            block = self._block(start, stop)
            self.n_generated = stop
            self._forget(stop)
        return block.T.copy(), first

    def _block(self, start: int, stop: int) -> np.ndarray:
        """Samples ``start:stop``, channels first (n_eeg + 1, stop - start)."""
        n = stop - start
        out = np.zeros((len(self.ch_names), n), dtype=np.float32)
        if n == 0:
            return out
        eeg = out[:-1]
        self._add_background(eeg, start, stop)
        for pattern, source in self._line:
            eeg += pattern[:, None] * source(start, stop)[None, :]
        white = self._noise_rng.standard_normal((n, eeg.shape[0])).T
        noise, self._noise_state = signal.lfilter(
            self._noise_b, self._noise_a, white, axis=1, zi=self._noise_state
        )
        eeg += noise.astype(np.float32)
        for response in self._responses:
            lo = max(start, response.onset)
            hi = min(stop, response.onset + response.evoked.shape[1])
            if lo < hi:
                eeg[:, lo - start : hi - start] += response.evoked[
                    :, lo - response.onset : hi - response.onset
                ]
            p_hi = min(stop, response.onset + self._pulse)
            if response.code and lo < p_hi:
                out[-1, lo - start : p_hi - start] = response.code
        return out

    def _segment_data(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Background segment ``k``: channel mix (n_eeg, segment + fade) and blink train."""
        if k not in self._segments:
            rng = self._stream(_STREAM_BACKGROUND, k)
            n = self._segment + self._fade
            sfreq = self.sfreq
            peak = self._alpha_peak
            sources = np.vstack(
                [
                    colored_noise(
                        rng, N_BRAIN_SOURCES, n, sfreq, lambda f: (f**2 + 0.5**2) ** (-1.5 / 4)
                    ),
                    colored_noise(rng, 1, n, sfreq, lambda f: np.exp(-0.5 * (f - peak) ** 2)),
                    colored_noise(
                        rng, N_DRIFT_SOURCES, n, sfreq, lambda f: 1.0 / (f + 0.01) * (f < 0.5)
                    ),
                ]
            )
            blink_rng = self._stream(_STREAM_BLINKS, k)
            blinks = blink_train(blink_rng, self._segment, sfreq)
            self._segments[k] = (self._background_mixing @ sources, blinks)
        return self._segments[k]

    def _add_background(self, eeg: np.ndarray, start: int, stop: int) -> None:
        """Add the cross-faded background and blinks of samples ``start:stop``."""
        seg, fade = self._segment, self._fade
        for k in range(start // seg, (stop - 1) // seg + 1):
            lo, hi = max(start, k * seg), min(stop, (k + 1) * seg)
            mix, blinks = self._segment_data(k)
            local = np.arange(lo, hi) - k * seg
            part = mix[:, lo - k * seg : hi - k * seg]
            if k > 0 and local[0] < fade:
                n_fade = min(fade, local[-1] + 1) - local[0]
                theta = 0.5 * math.pi * (local[:n_fade] + 0.5) / fade
                previous, _ = self._segment_data(k - 1)
                tail = previous[:, seg + local[:n_fade]]
                part = part.copy()
                part[:, :n_fade] = part[:, :n_fade] * np.sin(theta) + tail * np.cos(theta)
            eeg[:, lo - start : hi - start] += part
            eeg[:, lo - start : hi - start] += self._blink_pattern[:, None] * blinks[local]

    def _forget(self, generated: int) -> None:
        """Drop background segments and responses that lie wholly before ``generated``."""
        current = generated // self._segment
        for k in [k for k in self._segments if k < current - 1]:
            del self._segments[k]
        self._responses = [r for r in self._responses if r.onset + r.evoked.shape[1] > generated]
