"""A virtual subject: realistic **synthetic** observation-ErrP EEG (docs/eeg.md).

No real ErrP recordings can be downloaded here, so tests, demos and benchmarks use this
generator. Everything it makes is marked ``SYNTHETIC`` in ``raw.info["description"]`` (and in
the BDF header written by :func:`services.eeg.recordings.io.write_bdf`).

Signal model (64 BioSemi channels, volts), all drawn from one seeded generator:

* **Error trials** carry the fronto-central observation-ErrP difference wave: a positivity
  at ~200 ms and a negativity at ~250 ms (FCz maximum), a wider positivity at ~320 ms and a
  late negativity at ~450 ms (Cz maximum), each falling off with scalp distance.
* **Correct trials** carry a weaker, later P300-like centro-parietal bump.
* **Both** carry an occipital visual evoked response to the robot's movement, which is the
  same for both classes and therefore carries no label information.
* Per-trial amplitude jitter (20 % SD) and latency jitter (time-stretch SD 10 %, clipped to
  +-20 %), a per-subject
  latency shift (uniform in +-100 ms unless given) and per-subject topography jitter.
* Background: 24 spatially smooth 1/f^1.5 brain sources (volume conduction, so spatial
  filters cannot average the noise away), occipital alpha (8-12 Hz, subject-specific peak),
  frontal eye blinks (Poisson, ~15 per minute), 50 Hz line noise with a 100 Hz harmonic,
  slow electrode drift, channel-local noise (independent per channel, 1/f^2 above 3 Hz, so
  no spatial filter can cancel all of the noise) and white amplifier noise.

``quality`` in [0, 1] is the single per-subject knob: it scales every label-dependent
component (the error wave and the correct-trial bump) by ``quality * ERRP_GAIN``, so
``quality=0`` has no ErrP at all, ``quality=0.36`` has the typical amplitudes below and
``quality=1`` is the clearest subject the generator makes. The background does not
depend on ``quality``, so two subjects with the same seed differ only in their ErrP.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import mne
import numpy as np
from scipy import fft, signal

from services.core.actions import ACTION_PERIOD_S, TRIGGER_CORRECT, TRIGGER_ERROR
from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_TAG, TRIGGER_PULSE_S

MONTAGE_NAME = "biosemi64"
MIN_SFREQ = 256.0
"""Lowest sampling rate the generator accepts (the 100 Hz line harmonic must be representable)."""
ERP_WINDOW_S = 1.3
"""Length after each onset over which evoked responses are synthesised (s)."""
MAX_SUBJECT_SHIFT_S = 0.1
TRIAL_AMPLITUDE_JITTER = 0.2
TRIAL_LATENCY_JITTER = 0.1


@dataclass(frozen=True)
class ErpComponent:
    """One Gaussian-shaped evoked component.

    Parameters
    ----------
    amplitude_uv : float
        Peak amplitude at the topography centre (microvolts).
    latency_s : float
        Peak latency after the action onset (s), before subject shift and trial jitter.
    width_s : float
        Standard deviation of the Gaussian in time (s).
    centre : str
        Electrode at which the topography peaks.
    spread_m : float
        Standard deviation of the Gaussian topography along the scalp (m).
    """

    amplitude_uv: float
    latency_s: float
    width_s: float
    centre: str
    spread_m: float


ERROR_COMPONENTS: tuple[ErpComponent, ...] = (
    ErpComponent(3.0, 0.200, 0.018, "FCz", 0.055),
    ErpComponent(-6.5, 0.250, 0.022, "FCz", 0.055),
    ErpComponent(7.5, 0.320, 0.045, "Cz", 0.065),
    ErpComponent(-4.0, 0.450, 0.055, "Cz", 0.065),
)
"""The observation-ErrP on error trials, typical amplitudes (``quality=0.36``)."""

CORRECT_COMPONENTS: tuple[ErpComponent, ...] = (ErpComponent(2.0, 0.350, 0.060, "CPz", 0.07),)
"""The weaker P300-like bump on correct trials, typical amplitude (``quality=0.36``)."""

VISUAL_COMPONENTS: tuple[ErpComponent, ...] = (
    ErpComponent(3.0, 0.100, 0.015, "Oz", 0.05),
    ErpComponent(-4.0, 0.170, 0.022, "POz", 0.06),
)
"""Visual response to the robot moving: the same on every trial, independent of quality."""

ERRP_GAIN = 2.8
"""Gain of the label-dependent components at ``quality=1``: the amplitudes above are a typical
subject's (``quality=0.36``); the clearest subject has 2.8 times larger ErrPs."""
N_BRAIN_SOURCES = 24
BRAIN_RMS_UV = 15.0
ALPHA_RMS_UV = 9.0
BLINK_PEAK_UV = 150.0
BLINKS_PER_MINUTE = 15.0
LINE_FREQ_HZ = 50.0
LINE_RMS_UV = 4.0
N_DRIFT_SOURCES = 4
DRIFT_RMS_UV = 25.0
LOCAL_NOISE_UV = 4.0
LOCAL_NOISE_CORNER_HZ = 3.0
SENSOR_NOISE_UV = 1.0


@dataclass(frozen=True)
class VirtualSubject:
    """A synthetic subject: ErrP quality, seed and latency shift.

    Parameters
    ----------
    quality : float
        ErrP strength in [0, 1]; 0 means no label-dependent signal at all.
    seed : int
        Seed of every random draw (topographies, background, artifacts, jitter).
    latency_shift_s : float | None
        Subject latency shift (s, within +-0.1); drawn from ``seed`` when None.
    """

    quality: float
    seed: int
    latency_shift_s: float | None = None

    def __post_init__(self) -> None:
        if not (0.0 <= self.quality <= 1.0) or math.isnan(self.quality):
            raise ValueError(f"quality must be in [0, 1], got {self.quality}")
        if self.latency_shift_s is not None and abs(self.latency_shift_s) > MAX_SUBJECT_SHIFT_S:
            raise ValueError(
                f"latency_shift_s must be within +-{MAX_SUBJECT_SHIFT_S} s, "
                f"got {self.latency_shift_s}"
            )

    def simulate(
        self,
        labels: Sequence[bool],
        *,
        action_period_s: float = ACTION_PERIOD_S,
        sfreq: float = 2048.0,
        lead_in_s: float = 2.0,
    ) -> mne.io.RawArray:
        """Simulate this subject watching ``labels`` (see :func:`simulate_recording`)."""
        return simulate_recording(
            labels,
            quality=self.quality,
            seed=self.seed,
            action_period_s=action_period_s,
            sfreq=sfreq,
            lead_in_s=lead_in_s,
            latency_shift_s=self.latency_shift_s,
        )


def montage() -> mne.channels.DigMontage:
    """The BioSemi 64-channel montage (bundled with MNE, no download)."""
    return mne.channels.make_standard_montage(MONTAGE_NAME)


def eeg_channel_names() -> list[str]:
    """The 64 EEG channel names in BioSemi order."""
    return list(montage().ch_names)


def electrode_positions() -> tuple[list[str], np.ndarray]:
    """The montage's channel names and their positions (m), shape (n_channels, 3)."""
    mont = montage()
    pos = mont.get_positions()["ch_pos"]
    names = list(mont.ch_names)
    return names, np.array([pos[name] for name in names])


def topography(positions: np.ndarray, centre: np.ndarray, spread_m: float) -> np.ndarray:
    """Gaussian fall-off with chord distance from ``centre`` (peak 1 at the centre)."""
    d2 = np.sum((positions - centre) ** 2, axis=1)
    return np.exp(-d2 / (2.0 * spread_m**2))


def colored_noise(
    rng: np.random.Generator, n_sources: int, n_times: int, sfreq: float, amplitude_fn
) -> np.ndarray:
    """``n_sources`` rows of Gaussian noise with spectrum ``|amplitude_fn(f)|``, unit RMS."""
    n_fft = fft.next_fast_len(n_times, real=True)
    freqs = fft.rfftfreq(n_fft, d=1.0 / sfreq)
    shape = amplitude_fn(freqs).astype(np.float32)
    shape[0] = 0.0
    out = np.empty((n_sources, n_times), dtype=np.float32)
    for k in range(n_sources):
        spectrum = np.empty(freqs.size, dtype=np.complex64)
        spectrum.real = rng.standard_normal(freqs.size, dtype=np.float32)
        spectrum.imag = rng.standard_normal(freqs.size, dtype=np.float32)
        spectrum *= shape
        row = fft.irfft(spectrum, n=n_fft)[:n_times]
        rms = float(np.sqrt(np.mean(np.square(row, dtype=np.float64))))
        out[k] = row / rms if rms > 0 else row
    return out


def component_waveforms(
    components: Sequence[ErpComponent],
    n_trials: int,
    times: np.ndarray,
    shift_s: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Per-trial waveforms (n_components, n_trials, n_window) with amplitude/latency jitter."""
    amp = rng.normal(1.0, TRIAL_AMPLITUDE_JITTER, size=(len(components), n_trials)).clip(0.0)
    stretch = rng.normal(1.0, TRIAL_LATENCY_JITTER, size=n_trials).clip(0.8, 1.2)
    waves = np.empty((len(components), n_trials, times.size))
    for c, comp in enumerate(components):
        latency = max(comp.latency_s + shift_s, 0.05) * stretch[:, None]
        width = comp.width_s * stretch[:, None]
        waves[c] = amp[c, :, None] * np.exp(-0.5 * ((times[None, :] - latency) / width) ** 2)
    return waves


def blink_train(rng: np.random.Generator, n_times: int, sfreq: float) -> np.ndarray:
    """Unit-peak blink waveforms at Poisson times (a ~250 ms asymmetric bump)."""
    duration_s = n_times / sfreq
    n_blinks = rng.poisson(BLINKS_PER_MINUTE * duration_s / 60.0)
    train = np.zeros(n_times, dtype=np.float32)
    t = np.arange(int(0.5 * sfreq)) / sfreq
    shape = (t / 0.08) ** 2 * np.exp(2.0 * (1.0 - t / 0.08))  # gamma-like, peak 1 at 80 ms
    for start in rng.integers(0, max(n_times - t.size, 1), size=n_blinks):
        seg = train[start : start + t.size]
        seg += (rng.uniform(0.6, 1.2) * shape[: seg.size]).astype(np.float32)
    return train


GENERATION_BLOCK = 1 << 18
"""Samples mixed per block (the white-noise draws follow this blocking, so it is fixed)."""


class SyntheticRecording:
    """A virtual subject's recording, generated block by block in float32.

    The slow-varying sources (evoked responses, background, alpha, blinks, drift) are drawn
    once, in float32, when the object is made (~0.4 GB for 20 minutes at 2048 Hz); the
    channels are mixed, and the channel-local noise drawn, block by block on every pass of
    :meth:`iter_chunks`, which always yields the same samples. Nothing holds the whole
    recording unless :meth:`to_raw` is called. Arguments as :func:`simulate_recording`.

    Attributes
    ----------
    info : mne.Info
        64 EEG channels (``biosemi64`` montage) and ``Status``; the description starts
        with ``"SYNTHETIC"``.
    n_times : int
        Samples per channel.
    """

    def __init__(
        self,
        labels: Sequence[bool],
        *,
        quality: float,
        seed: int,
        action_period_s: float = ACTION_PERIOD_S,
        sfreq: float = 2048.0,
        lead_in_s: float = 2.0,
        latency_shift_s: float | None = None,
    ) -> None:
        subject = VirtualSubject(quality=quality, seed=seed, latency_shift_s=latency_shift_s)
        labels_arr = np.asarray([bool(v) for v in labels], dtype=bool)
        if labels_arr.size == 0:
            raise ValueError("labels is empty: at least one action is needed")
        if not (sfreq >= MIN_SFREQ) or not math.isfinite(sfreq):
            raise ValueError(f"sfreq must be a finite rate >= {MIN_SFREQ} Hz, got {sfreq}")
        if not (action_period_s > 0) or not math.isfinite(action_period_s):
            raise ValueError(f"action_period_s must be positive, got {action_period_s}")
        if not (lead_in_s >= 0) or not math.isfinite(lead_in_s):
            raise ValueError(f"lead_in_s must be >= 0, got {lead_in_s}")

        rng = np.random.default_rng(seed)
        shift_s = (
            float(rng.uniform(-MAX_SUBJECT_SHIFT_S, MAX_SUBJECT_SHIFT_S))
            if subject.latency_shift_s is None
            else float(subject.latency_shift_s)
        )
        n_actions = labels_arr.size
        n_times = round((2 * lead_in_s + n_actions * action_period_s) * sfreq)
        onsets = np.round((lead_in_s + np.arange(n_actions) * action_period_s) * sfreq).astype(int)
        names, positions = electrode_positions()
        index = {name: i for i, name in enumerate(names)}
        n_chans = len(names)

        # Every component is a source time course times a spatial pattern (volts per unit);
        # all of them are mixed into the channels with a single matrix product per block.
        # A source is a float32 row, or a function (start, stop) -> float32 for the cheap
        # deterministic ones (line noise), made per block.
        patterns: list[np.ndarray] = []
        sources: list[np.ndarray | Callable[[int, int], np.ndarray]] = []

        # Evoked responses, one source per component.
        win = np.arange(round(ERP_WINDOW_S * sfreq)) / sfreq
        groups = (
            (ERROR_COMPONENTS, ~labels_arr, subject.quality * ERRP_GAIN),
            (CORRECT_COMPONENTS, labels_arr, subject.quality * ERRP_GAIN),
            (VISUAL_COMPONENTS, np.ones(n_actions, dtype=bool), 1.0),
        )
        topo_jitter = rng.normal(0.0, 0.008, size=(3, 3))
        for g, (components, mask, gain) in enumerate(groups):
            waves = component_waveforms(components, n_actions, win, shift_s, rng)
            for c, comp in enumerate(components):
                course = np.zeros(n_times, dtype=np.float32)
                trial_onsets = onsets[mask]
                idx = trial_onsets[:, None] + np.arange(win.size)[None, :]
                keep = idx < n_times
                np.add.at(course, idx[keep], waves[c][mask][keep].astype(np.float32))
                centre = positions[index[comp.centre]] + topo_jitter[g]
                patterns.append(
                    gain * comp.amplitude_uv * 1e-6 * topography(positions, centre, comp.spread_m)
                )
                sources.append(course)

        # Background brain activity: smooth random topographies, 1/f^1.5 spectrum.
        brain = colored_noise(
            rng, N_BRAIN_SOURCES, n_times, sfreq, lambda f: (f**2 + 0.5**2) ** (-1.5 / 4)
        )
        brain_patterns = np.empty((N_BRAIN_SOURCES, n_chans))
        for k in range(N_BRAIN_SOURCES):
            centre = positions[rng.integers(n_chans)] * rng.uniform(0.6, 1.0)
            brain_patterns[k] = rng.choice([-1.0, 1.0]) * topography(
                positions, centre, rng.uniform(0.03, 0.07)
            )
        channel_rms = np.sqrt(np.sum(brain_patterns**2, axis=0))
        brain_patterns *= BRAIN_RMS_UV * 1e-6 / np.sqrt(np.mean(channel_rms**2))
        patterns.extend(brain_patterns)
        sources.extend(brain)

        # Occipital alpha with a subject-specific peak frequency.
        alpha_peak = rng.uniform(9.0, 11.0)
        alpha = colored_noise(
            rng, 1, n_times, sfreq, lambda f: np.exp(-0.5 * ((f - alpha_peak) / 1.0) ** 2)
        )
        patterns.append(ALPHA_RMS_UV * 1e-6 * topography(positions, positions[index["Oz"]], 0.05))
        sources.append(alpha[0])

        # Eye blinks: frontal, decaying towards the back of the head.
        eye = np.array([0.0, 0.11, -0.02])
        patterns.append(BLINK_PEAK_UV * 1e-6 * topography(positions, eye, 0.045))
        sources.append(blink_train(rng, n_times, sfreq))

        # Line noise: two quadrature components with independent per-channel gains (phase
        # varies), computed per block.
        for freq, rel in ((LINE_FREQ_HZ, 1.0), (2 * LINE_FREQ_HZ, 0.25)):
            for trig in (np.sin, np.cos):
                patterns.append(rel * LINE_RMS_UV * 1e-6 * rng.uniform(0.2, 1.0, n_chans))
                sources.append(line_source(trig, freq, sfreq))

        # Slow electrode drift, different on every channel.
        drift = colored_noise(
            rng, N_DRIFT_SOURCES, n_times, sfreq, lambda f: 1.0 / (f + 0.01) * (f < 0.5)
        )
        patterns.extend(DRIFT_RMS_UV * 1e-6 * rng.normal(0, 1, (N_DRIFT_SOURCES, n_chans)) / 2.0)
        sources.extend(drift)

        # Channel-local noise (electrode, skin, nearby muscle) plus white amplifier noise,
        # both independent per channel, so no spatial filter can cancel them: one white
        # sequence through (g / (1 - pole z^-1)) * (1 - pole) + sensor, i.e. a one-pole
        # low-pass (1/f^2 above LOCAL_NOISE_CORNER_HZ) plus a flat floor; filter state
        # carried across blocks.
        pole = math.exp(-2.0 * math.pi * LOCAL_NOISE_CORNER_HZ / sfreq)
        local_gain = LOCAL_NOISE_UV * 1e-6 * math.sqrt(1.0 - pole**2) / (1.0 - pole)
        sensor = SENSOR_NOISE_UV * 1e-6
        self._noise_b = np.array(
            [(1.0 - pole) * local_gain + sensor, -pole * sensor], dtype=np.float32
        )
        self._noise_a = np.array([1.0, -pole], dtype=np.float32)
        self._noise_state = rng.standard_normal((n_chans, 1), dtype=np.float32) * np.float32(
            LOCAL_NOISE_UV * 1e-6
        )
        self._noise_rng_state = rng.bit_generator.state
        self._mixing = np.asarray(patterns, dtype=np.float32).T  # (n_chans, n_sources)
        self._sources = sources

        status = np.zeros(n_times, dtype=np.float32)
        pulse = max(1, round(TRIGGER_PULSE_S * sfreq))
        codes = np.where(labels_arr, TRIGGER_CORRECT, TRIGGER_ERROR)
        for onset, code in zip(onsets, codes, strict=True):
            status[onset : onset + pulse] = code
        self._status = status

        self.n_times = n_times
        self.info = mne.create_info([*names, STIM_CHANNEL], sfreq, ["eeg"] * n_chans + ["stim"])
        self.info["description"] = (
            f"{SYNTHETIC_TAG} virtual subject quality={subject.quality:g} seed={seed} "
            f"shift={shift_s:+.3f}s"
        )
        self.info.set_montage(montage(), verbose="error")

    @property
    def ch_names(self) -> list[str]:
        return list(self.info["ch_names"])

    def iter_chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(first_sample, block)``: all channels, float32 (n_channels, <= 2**18).

        EEG in volts, ``Status`` codes in the last row. Every pass yields the same samples.
        """
        rng = np.random.default_rng()
        rng.bit_generator.state = self._noise_rng_state
        noise_state = self._noise_state
        n_chans = self._mixing.shape[0]
        for start in range(0, self.n_times, GENERATION_BLOCK):
            stop = min(start + GENERATION_BLOCK, self.n_times)
            stacked = np.stack(
                [s(start, stop) if callable(s) else s[start:stop] for s in self._sources]
            )
            block = np.empty((n_chans + 1, stop - start), dtype=np.float32)
            mixed = self._mixing @ stacked
            del stacked
            white = rng.standard_normal(mixed.shape, dtype=np.float32)
            noise, noise_state = signal.lfilter(
                self._noise_b, self._noise_a, white, axis=1, zi=noise_state
            )
            del white
            np.add(mixed, noise, out=block[:n_chans])
            block[n_chans] = self._status[start:stop]
            yield start, block

    def to_raw(self) -> mne.io.RawArray:
        """The whole recording as an MNE ``RawArray`` (float64: 8 bytes per sample)."""
        data = np.empty((len(self.info["ch_names"]), self.n_times), dtype=np.float64)
        for start, block in self.iter_chunks():
            data[:, start : start + block.shape[1]] = block
        raw = mne.io.RawArray(data, self.info, verbose="error")
        return raw


def line_source(trig, freq: float, sfreq: float) -> Callable[[int, int], np.ndarray]:
    """Samples ``start:stop`` of sqrt(2) * trig(2 pi freq t), float32 (unit RMS)."""

    def samples(start: int, stop: int) -> np.ndarray:
        t = np.arange(start, stop) / sfreq
        return (math.sqrt(2.0) * trig(2 * np.pi * freq * t)).astype(np.float32)

    return samples


def simulate_recording(
    labels: Sequence[bool],
    *,
    quality: float,
    seed: int,
    action_period_s: float = ACTION_PERIOD_S,
    sfreq: float = 2048.0,
    lead_in_s: float = 2.0,
    latency_shift_s: float | None = None,
) -> mne.io.RawArray:
    """Simulate a synthetic 64-channel recording of a subject watching labelled actions.

    Parameters
    ----------
    labels : sequence of bool
        ``labels[i]`` is True when action ``i`` was correct (oracle-optimal), False for an
        error. One action is shown every ``action_period_s``, the first at ``lead_in_s``.
    quality : float
        ErrP strength in [0, 1] (0: no ErrP at all, 1: the clearest subject).
    seed : int
        Seed of every random draw; the same arguments give the same recording.
    action_period_s : float
        Time between action onsets (s).
    sfreq : float
        Sampling rate (Hz), at least 256.
    lead_in_s : float
        Time before the first action, and after the last action's period (s).
    latency_shift_s : float | None
        Subject latency shift of the ErrP (s, within +-0.1); drawn from ``seed`` when None.

    Returns
    -------
    raw : mne.io.RawArray
        64 EEG channels in volts (BioSemi names, ``biosemi64`` montage set) and a stim
        channel ``"Status"`` with a 10 ms pulse of 1 (correct) or 2 (error) at each onset.
        ``raw.info["description"]`` starts with ``"SYNTHETIC"``. It holds the whole
        recording in float64; :class:`SyntheticRecording` generates it block by block.
    """
    return SyntheticRecording(
        labels,
        quality=quality,
        seed=seed,
        action_period_s=action_period_s,
        sfreq=sfreq,
        lead_in_s=lead_in_s,
        latency_shift_s=latency_shift_s,
    ).to_raw()


def stream_samples(
    raw: mne.io.BaseRaw, *, chunk_samples: int = 64
) -> Iterator[tuple[np.ndarray, int]]:
    """Yield a recording in chunks as a live amplifier would deliver it.

    Parameters
    ----------
    raw : mne.io.BaseRaw
        A preloaded recording (e.g. from :func:`simulate_recording`).
    chunk_samples : int
        Samples per chunk (64 at 2048 Hz is one 31 ms BioSemi-like block).

    Yields
    ------
    samples : ndarray, shape (n_times, n_channels)
        All channels of the chunk (volts for EEG, codes for ``Status``), time first.
    first_sample : int
        Index of the chunk's first sample in the recording.
    """
    if chunk_samples < 1:
        raise ValueError(f"chunk_samples must be >= 1, got {chunk_samples}")
    data = raw.get_data()
    for start in range(0, data.shape[1], chunk_samples):
        yield data[:, start : start + chunk_samples].T.copy(), start
