"""Causal preprocessing: offline == online, epoch length and timing, filter response."""

from __future__ import annotations

import numpy as np
import pytest

from services.eeg.signal.preprocessing import (
    EpochUnavailableError,
    OnlinePreprocessor,
    PreprocessingParams,
)
from services.eeg.virtual.subject import simulate_recording

SFREQ = 2048.0
AGREEMENT_RTOL = 1e-6
"""Stated tolerance: max |online - offline| <= 1e-6 * max |offline| (in practice 0)."""


@pytest.fixture(scope="module")
def recording():
    """A short SYNTHETIC virtual-subject recording (24 actions, ~40 s)."""
    labels = np.random.default_rng(0).random(24) >= 0.3
    return simulate_recording(labels, quality=1.0, seed=3)


def _eeg(raw) -> tuple[np.ndarray, list[str]]:
    picks = [i for i, t in enumerate(raw.get_channel_types()) if t == "eeg"]
    return raw.get_data(picks=picks), [raw.ch_names[i] for i in picks]


def _onsets(raw) -> tuple[np.ndarray, np.ndarray]:
    stim = raw.get_data(picks="Status")[0]
    samples = np.flatnonzero(np.diff(stim, prepend=0) > 0)
    return samples, stim[samples].astype(int)


def test_epoch_length_rule() -> None:
    assert PreprocessingParams().n_times_epoch == 103
    assert PreprocessingParams(tmin=-0.2, tmax=0.8).n_times_epoch == 129
    assert PreprocessingParams(sfreq_out=256.0, antialias_cutoff=100.0).n_times_epoch == 206


def test_invalid_params_and_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="h_freq"):
        PreprocessingParams(l_freq=1.0, h_freq=70.0)
    with pytest.raises(ValueError, match="tmax"):
        PreprocessingParams(tmin=0.5, tmax=0.2)
    with pytest.raises(ValueError, match=r"below the feature rate 128\.0 Hz"):
        OnlinePreprocessor(["Cz"], 100.0)
    with pytest.raises(ValueError, match="by a ratio of integers up to 1000"):
        OnlinePreprocessor(["Cz"], 1000.001)
    pre = OnlinePreprocessor(["Cz", "Pz"], SFREQ)
    with pytest.raises(ValueError, match="shape"):
        pre.push(np.zeros((10, 3)), 0.0)
    bad = np.zeros((10, 2))
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        pre.push(bad, 0.0)


def test_chunked_stream_equals_single_push(recording) -> None:
    data, names = _eeg(recording)
    whole = OnlinePreprocessor(names, SFREQ, buffer_s=120.0)
    whole.push(data.T, 0.0)
    chunked = OnlinePreprocessor(names, SFREQ, buffer_s=120.0)
    rng = np.random.default_rng(1)
    i = 0
    while i < data.shape[1]:
        n = int(rng.integers(1, 3000))
        chunked.push(data[:, i : i + n].T, i / SFREQ)
        i += n
    assert whole.n_buffered == chunked.n_buffered == -(-data.shape[1] // 16)
    a = whole._data[:, whole._start : whole._stop]
    b = chunked._data[:, chunked._start : chunked._stop]
    assert np.max(np.abs(a - b)) <= AGREEMENT_RTOL * np.max(np.abs(a))
    np.testing.assert_allclose(
        whole._times[whole._start : whole._stop],
        chunked._times[chunked._start : chunked._stop],
        atol=1e-9,
    )


def test_offline_epochs_equal_live_epochs(recording) -> None:
    """epochs_from_raw (calibration path) == a live stream pushed in odd chunks."""
    from services.eeg.recordings.epochs import epochs_from_raw

    offline = epochs_from_raw(recording)
    samples, codes = _onsets(recording)
    assert offline.X.shape == (len(samples), 64, 103)
    assert offline.X.dtype == np.float32
    np.testing.assert_array_equal(offline.y, (codes == 2).astype(int))
    assert offline.synthetic

    data, names = _eeg(recording)
    t0 = 5021.37  # an LSL-like clock that does not start at 0
    live = OnlinePreprocessor(names, SFREQ, buffer_s=10.0)
    rng = np.random.default_rng(7)
    got = {}
    i = 0
    while i < data.shape[1]:
        n = int(rng.integers(16, 700))
        live.push(data[:, i : i + n].T, t0 + i / SFREQ)
        i += n
        for k, s in enumerate(samples):
            if k not in got:
                epoch = live.epoch_at(t0 + s / SFREQ)
                if epoch is not None:
                    got[k] = epoch
    assert sorted(got) == list(range(len(samples)))
    online = np.stack([got[k] for k in range(len(samples))])
    assert np.max(np.abs(online - offline.X)) <= AGREEMENT_RTOL * np.max(np.abs(offline.X))


def test_epoch_window_incomplete_then_expired() -> None:
    pre = OnlinePreprocessor(["Cz"], SFREQ, buffer_s=2.0)
    assert pre.epoch_at(0.0) is None
    pre.push(np.zeros((int(0.5 * SFREQ), 1)), 0.0)
    assert pre.epoch_at(0.1) is None  # window ends at 0.9 s, data only up to 0.5 s
    pre.push(np.zeros((int(0.5 * SFREQ), 1)), 0.5)
    assert pre.epoch_at(0.1).shape == (1, 103)
    pre.push(np.zeros((int(3 * SFREQ), 1)), 1.0)
    with pytest.raises(EpochUnavailableError, match="oldest"):
        pre.epoch_at(0.1)


def test_epoch_starts_at_nearest_sample() -> None:
    """Onsets within half a 128 Hz sample give the same epoch; beyond, it shifts by one."""
    pre = OnlinePreprocessor(["Cz"], SFREQ, buffer_s=10.0)
    pre.push(np.random.default_rng(0).normal(size=(int(4 * SFREQ), 1)), 0.0)
    ref = pre.epoch_at(1.0)
    np.testing.assert_array_equal(pre.epoch_at(1.0 + 0.4 / 128), ref)
    np.testing.assert_array_equal(pre.epoch_at(1.0 - 0.4 / 128), ref)
    np.testing.assert_array_equal(pre.epoch_at(1.0 + 0.6 / 128)[:, :-1], ref[:, 1:])
    np.testing.assert_array_equal(pre.epoch_at(1.0 - 0.6 / 128)[:, 1:], ref[:, :-1])


def _gain(freq: float, params: PreprocessingParams | None = None) -> float:
    """Steady-state output/input amplitude for a sinusoid at ``freq`` Hz."""
    t = np.arange(int(20 * SFREQ)) / SFREQ
    x = np.sin(2 * np.pi * freq * t)[:, None]
    pre = OnlinePreprocessor(["Cz"], SFREQ, params, buffer_s=30.0)
    pre.push(x, 0.0)
    y = pre._data[0, pre._start : pre._stop]
    return float(np.max(np.abs(y[len(y) // 2 :])))


def test_filter_response() -> None:
    assert _gain(10.0) == pytest.approx(1.0, abs=0.02)  # ErrP band passes
    assert _gain(4.0) == pytest.approx(1.0, abs=0.03)
    assert _gain(0.2) < 0.05  # drift removed
    assert _gain(60.0) < 0.2  # above the band
    assert _gain(100.0) < 0.01  # would alias to 28 Hz without the anti-alias filter
    assert _gain(120.0) < 0.01


def test_dc_offset_causes_no_transient() -> None:
    """A large electrode offset at stream start (BioSemi: tens of mV) does not ring."""
    x = np.full((int(5 * SFREQ), 1), 0.03)
    pre = OnlinePreprocessor(["Cz"], SFREQ)
    pre.push(x, 0.0)
    assert np.max(np.abs(pre._data[0, pre._start : pre._stop])) < 1e-9


def test_reset_forgets_state() -> None:
    pre = OnlinePreprocessor(["Cz"], SFREQ)
    pre.push(np.ones((4096, 1)), 0.0)
    pre.reset()
    assert pre.n_buffered == 0 and pre.latest_timestamp is None


@pytest.mark.parametrize(
    ("sfreq", "up", "down"),
    [(250.0, 64, 125), (500.0, 32, 125), (1000.0, 16, 125), (2048.0, 1, 16), (128.0, 1, 1)],
)
def test_offline_equals_online_at_every_rate(sfreq, up, down) -> None:
    """The calibration path and a live stream in odd chunks agree at any rate >= 128 Hz."""
    from services.eeg.recordings.epochs import epochs_from_raw
    from tests.eeg.caps import CAP_8, LABELS, virtual_recording

    raw = virtual_recording(sfreq if sfreq >= 250 else 1000.0, CAP_8, seed=2)
    if sfreq == 128.0:
        raw = _resampled_copy(raw, 128.0)
    pre = OnlinePreprocessor(CAP_8, sfreq)
    assert (pre.up, pre.down) == (up, down)
    offline = epochs_from_raw(raw)
    assert offline.X.shape == (len(LABELS), 8, 103)
    np.testing.assert_array_equal(offline.y, [0 if ok else 1 for ok in LABELS])
    data, names = _eeg(raw)
    samples, _ = _onsets(raw)
    live = OnlinePreprocessor(names, sfreq, buffer_s=10.0)
    rng = np.random.default_rng(int(sfreq))
    got: dict[int, np.ndarray] = {}
    i = 0
    while i < data.shape[1]:
        n = int(rng.integers(1, 400))
        live.push(data[:, i : i + n].T, 77.5 + i / sfreq)
        i += n
        for k, s in enumerate(samples):
            if k not in got and (epoch := live.epoch_at(77.5 + s / sfreq)) is not None:
                got[k] = epoch
    online = np.stack([got[k] for k in range(len(samples))])
    assert np.max(np.abs(online - offline.X)) <= AGREEMENT_RTOL * np.max(np.abs(offline.X))


def _resampled_copy(raw, sfreq: float):
    """``raw`` at ``sfreq`` (EEG by resample_poly, action pulses on the nearest sample)."""
    import mne
    from scipy import signal

    ratio = sfreq / raw.info["sfreq"]
    up, down = round(sfreq), round(raw.info["sfreq"])
    eeg = signal.resample_poly(raw.get_data(picks="eeg"), up, down, axis=1)
    samples, codes = _onsets(raw)
    status = np.zeros(eeg.shape[1])
    status[np.round(samples * ratio).astype(int)] = codes
    names = [raw.ch_names[i] for i in mne.pick_types(raw.info, eeg=True)]
    info = mne.create_info([*names, "Status"], sfreq, ["eeg"] * len(names) + ["stim"])
    return mne.io.RawArray(np.vstack([eeg, status[None]]), info, verbose="error")


def test_rational_resampling_is_delay_compensated_and_rate_independent() -> None:
    """A 6 Hz burst comes out the same (timing and amplitude) from 250, 500 and 1000 Hz."""
    outputs = {}
    for sfreq in (250.0, 500.0, 1000.0):
        t = np.arange(round(8 * sfreq)) / sfreq
        burst = np.sin(2 * np.pi * 6 * t) * np.exp(-0.5 * ((t - 5.0) / 0.15) ** 2) * 1e-5
        pre = OnlinePreprocessor(["Cz"], sfreq, buffer_s=20.0)
        pre.push(burst[:, None], 0.0)
        times = pre._times[pre._start : pre._stop]
        keep = (times >= 3.0) & (times < 7.0)
        np.testing.assert_allclose(times[keep][:2], [3.0, 3.0 + 1 / 128], atol=1e-9)
        outputs[sfreq] = pre._data[0, pre._start : pre._stop][keep]
    peak = np.max(np.abs(outputs[1000.0]))
    assert np.max(np.abs(outputs[250.0] - outputs[1000.0])) < 0.01 * peak
    assert np.max(np.abs(outputs[500.0] - outputs[1000.0])) < 0.01 * peak
