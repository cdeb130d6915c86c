"""The virtual subject: shapes, markers, determinism, the ErrP in the grand average."""

from __future__ import annotations

import mne
import numpy as np
import pytest
from scipy import signal

from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.virtual.subject import (
    VirtualSubject,
    eeg_channel_names,
    simulate_recording,
    stream_samples,
)

SFREQ = 512.0


def _labels(n: int, seed: int = 0) -> list[bool]:
    return (np.random.default_rng(seed).random(n) < 0.4).tolist()


def _difference_wave(raw: mne.io.BaseRaw, channel: str) -> tuple[np.ndarray, np.ndarray]:
    """Grand average error minus correct at ``channel`` (uV), 1-40 Hz band, 0..0.8 s."""
    sfreq = raw.info["sfreq"]
    sos = signal.butter(4, [1.0, 40.0], btype="band", fs=sfreq, output="sos")
    data = signal.sosfiltfilt(sos, raw.get_data(picks=[channel])[0])
    events = mne.find_events(raw, stim_channel=STIM_CHANNEL, shortest_event=1, verbose=False)
    n = int(0.8 * sfreq)
    epochs = np.stack([data[s : s + n] for s in events[:, 0]])
    error = events[:, 2] == 2
    return np.arange(n) / sfreq, (epochs[error].mean(0) - epochs[~error].mean(0)) * 1e6


def test_shapes_channels_markers_and_synthetic_tag():
    labels = [True, False, False, True, False]
    raw = simulate_recording(labels, quality=0.5, seed=1, sfreq=SFREQ, lead_in_s=1.0)
    assert raw.ch_names == [*eeg_channel_names(), STIM_CHANNEL]
    assert len(raw.ch_names) == 65
    assert raw.get_channel_types()[-1] == "stim"
    assert raw.get_montage() is not None
    assert raw.info["description"].startswith("SYNTHETIC")
    assert raw.n_times == int((2 * 1.0 + 5 * 1.5) * SFREQ)
    events = mne.find_events(raw, stim_channel=STIM_CHANNEL, shortest_event=1, verbose=False)
    assert events[:, 2].tolist() == [1, 2, 2, 1, 2]
    expected = np.round((1.0 + 1.5 * np.arange(5)) * SFREQ).astype(int)
    np.testing.assert_array_equal(events[:, 0], expected)
    eeg = raw.get_data(picks="eeg")
    rms_uv = eeg.std(axis=1).mean() * 1e6
    assert 10.0 < rms_uv < 100.0, rms_uv  # tens of microvolts, in volts in the array


def test_deterministic_per_seed_and_seed_matters():
    labels = _labels(6)
    a = simulate_recording(labels, quality=0.7, seed=3, sfreq=SFREQ).get_data()
    b = simulate_recording(labels, quality=0.7, seed=3, sfreq=SFREQ).get_data()
    c = simulate_recording(labels, quality=0.7, seed=4, sfreq=SFREQ).get_data()
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a[:64], c[:64])


def test_quality_zero_and_one_share_background():
    """Quality only scales the label-dependent signal; the background is the same."""
    labels = _labels(8)
    zero = simulate_recording(labels, quality=0.0, seed=5, sfreq=SFREQ, latency_shift_s=0.0)
    one = simulate_recording(labels, quality=1.0, seed=5, sfreq=SFREQ, latency_shift_s=0.0)
    diff = (one.get_data(picks="eeg") - zero.get_data(picks="eeg")) * 1e6
    fcz = one.ch_names.index("FCz")
    assert np.abs(diff[fcz]).max() > 5.0  # the ErrP is there at quality 1
    events = mne.find_events(one, stim_channel=STIM_CHANNEL, shortest_event=1, verbose=False)
    assert np.abs(diff[:, : events[0, 0]]).max() < 1e-3  # nothing before the first action


def test_errp_in_grand_average_at_fcz_near_expected_latency():
    raw = simulate_recording(_labels(200, 1), quality=1.0, seed=2, sfreq=SFREQ, latency_shift_s=0)
    times, diff = _difference_wave(raw, "FCz")
    neg = (times > 0.2) & (times < 0.3)
    pos = (times > 0.28) & (times < 0.4)
    assert diff[neg].min() < -4.0, diff[neg].min()
    assert diff[pos].max() > 4.0, diff[pos].max()
    assert 0.22 <= times[neg][np.argmin(diff[neg])] <= 0.28
    # Occipital channels see much less of it than the fronto-central peak.
    _, diff_oz = _difference_wave(raw, "Oz")
    assert abs(diff_oz[pos].mean()) < 0.5 * diff[pos].mean()


def test_no_errp_at_quality_zero():
    raw = simulate_recording(_labels(200, 1), quality=0.0, seed=2, sfreq=SFREQ)
    _, diff = _difference_wave(raw, "FCz")
    assert np.abs(diff).max() < 4.0  # noise only (standard error ~1.5 uV)


def test_subject_latency_shift_moves_the_negativity():
    labels = _labels(200, 1)
    early = simulate_recording(labels, quality=1.0, seed=2, sfreq=SFREQ, latency_shift_s=-0.08)
    late = simulate_recording(labels, quality=1.0, seed=2, sfreq=SFREQ, latency_shift_s=0.08)
    times, d_early = _difference_wave(early, "FCz")
    _, d_late = _difference_wave(late, "FCz")
    window = (times > 0.1) & (times < 0.4)
    t_early = times[window][np.argmin(d_early[window])]
    t_late = times[window][np.argmin(d_late[window])]
    assert 0.1 < t_late - t_early < 0.22


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"quality": 1.5}, "quality"),
        ({"quality": -0.1}, "quality"),
        ({"sfreq": 100.0}, "sfreq"),
        ({"latency_shift_s": 0.3}, "latency_shift_s"),
        ({"action_period_s": 0.0}, "action_period_s"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    args = {"quality": 0.5, "seed": 0, "sfreq": SFREQ, **kwargs}
    with pytest.raises(ValueError, match=match):
        simulate_recording([True], **args)


def test_empty_labels_raise():
    with pytest.raises(ValueError, match="empty"):
        simulate_recording([], quality=0.5, seed=0)


def test_virtual_subject_and_stream_samples():
    subject = VirtualSubject(quality=0.5, seed=9, latency_shift_s=0.05)
    raw = subject.simulate([True, False], sfreq=SFREQ, lead_in_s=0.5)
    assert "seed=9" in raw.info["description"]
    chunks = list(stream_samples(raw, chunk_samples=100))
    assert [start for _, start in chunks] == list(range(0, raw.n_times, 100))
    joined = np.concatenate([c for c, _ in chunks], axis=0)
    np.testing.assert_array_equal(joined.T, raw.get_data())
