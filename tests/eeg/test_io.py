"""BDF writing and validated reading of recordings."""

from __future__ import annotations

import hashlib

import mne
import numpy as np
import pytest

from services.eeg.io import (
    RecordingError,
    action_events,
    file_sha256,
    is_synthetic,
    read_recording,
    write_bdf,
)
from services.eeg.virtual_subject import STIM_CHANNEL, simulate_recording

SFREQ = 512.0
LABELS = [True, False, False, True, False, False, True, False]


@pytest.fixture(scope="module")
def raw() -> mne.io.RawArray:
    return simulate_recording(LABELS, quality=0.8, seed=11, sfreq=SFREQ)


def test_bdf_round_trip_codes_data_and_synthetic_flag(raw, tmp_path):
    path = write_bdf(raw, tmp_path / "rec.bdf")
    assert path.read_bytes()[:8] == b"\xffBIOSEMI"
    assert not list(tmp_path.glob("*.part"))
    back = mne.io.read_raw_bdf(path, preload=True, verbose="error")
    assert back.ch_names == raw.ch_names
    assert back.info["sfreq"] == SFREQ
    np.testing.assert_array_equal(action_events(back), action_events(raw))
    assert action_events(back)[:, 2].tolist() == [1 if ok else 2 for ok in LABELS]
    status = back.get_data(picks=STIM_CHANNEL)[0]
    assert set(np.unique(status)) == {0.0, 1.0, 2.0}
    original = raw.get_data(picks="eeg")
    restored = back.get_data(picks="eeg")
    lsb = (original.max(axis=1) - original.min(axis=1)) / (2**24 - 1)
    assert np.all(np.abs(original - restored).max(axis=1) <= lsb * 0.51)
    validated = read_recording(path)
    assert is_synthetic(validated)
    assert validated.info["description"].startswith("SYNTHETIC virtual subject quality=0.8 seed=11")


def test_real_description_is_not_marked_synthetic(raw, tmp_path):
    real = raw.copy()
    real.info["description"] = "lab recording"
    back = read_recording(write_bdf(real, tmp_path / "real.bdf"))
    assert not is_synthetic(back)


def test_edf_and_fif_are_read(raw, tmp_path):
    fif = tmp_path / "rec_raw.fif"
    raw.save(fif, verbose="error")
    assert len(action_events(read_recording(fif))) == len(LABELS)
    assert is_synthetic(read_recording(fif))


def test_sha256(raw, tmp_path):
    path = write_bdf(raw, tmp_path / "rec.bdf")
    assert file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_write_bdf_rejects_nan_and_leaves_nothing(raw, tmp_path):
    bad = raw.copy()
    bad._data[3, 100] = np.nan
    with pytest.raises(ValueError, match="F1"):
        write_bdf(bad, tmp_path / "bad.bdf")
    assert list(tmp_path.iterdir()) == []


def _save(raw: mne.io.BaseRaw, tmp_path, name: str = "x_raw.fif"):
    path = tmp_path / name
    raw.save(path, verbose="error", overwrite=True)
    return path


def test_validation_errors_name_the_problem(raw, tmp_path):
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.bdf")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(RecordingError, match="unsupported format"):
        read_recording(tmp_path / "notes.txt")
    (tmp_path / "junk.bdf").write_bytes(b"not a bdf file at all" * 20)
    with pytest.raises(RecordingError, match="not a readable BDF"):
        read_recording(tmp_path / "junk.bdf")

    with pytest.raises(RecordingError, match="sampling rate 128 Hz"):
        read_recording(_save(raw.copy().resample(128.0, verbose="error"), tmp_path))
    with pytest.raises(RecordingError, match=r"1 of 64 required EEG channels missing \(Cz\)"):
        read_recording(_save(raw.copy().drop_channels(["Cz"]), tmp_path))
    with pytest.raises(RecordingError, match="no 'Status' trigger channel"):
        read_recording(_save(raw.copy().drop_channels([STIM_CHANNEL]), tmp_path))
    with pytest.raises(RecordingError, match=r"only 3\.00 s long"):
        read_recording(_save(raw.copy().crop(0, 3.0 - 1 / SFREQ), tmp_path))

    flat = raw.copy()
    flat._data[flat.ch_names.index("Pz")] = 0.0
    with pytest.raises(RecordingError, match=r"flat channels .*Pz"):
        read_recording(_save(flat, tmp_path))
    nan = raw.copy()
    nan._data[nan.ch_names.index("Oz"), 10:20] = np.nan
    with pytest.raises(RecordingError, match="NaN or infinite samples in channels Oz"):
        read_recording(_save(nan, tmp_path))
    silent = raw.copy()
    silent._data[-1] = 0.0
    with pytest.raises(RecordingError, match="no action trigger"):
        read_recording(_save(silent, tmp_path))


def test_action_events_ignore_biosemi_status_flags(raw):
    flagged = raw.copy()
    status = flagged._data[-1]
    flagged._data[-1] = np.where(status > 0, status + 0xFF00, 0xFF00)
    np.testing.assert_array_equal(action_events(flagged), action_events(raw))


def test_cli_subject_simulate_writes_a_valid_synthetic_bdf(tmp_path):
    from typer.testing import CliRunner

    from services.cli.main import app

    out = tmp_path / "subject.bdf"
    args = ["subject", "simulate", "--quality", "0.5", "--actions", "12", "--seed", "3"]
    result = CliRunner().invoke(app, [*args, "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert f"sha256 {file_sha256(out)}" in result.output
    assert "error fraction" in result.output
    recording = read_recording(out)
    assert is_synthetic(recording) and "quality=0.5 seed=3" in recording.info["description"]
    events = action_events(recording)
    assert len(events) == 12
    np.testing.assert_allclose(np.diff(events[:, 0]) / recording.info["sfreq"], 1.5)
    bad = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "subject.edf")])
    assert bad.exit_code != 0 and not (tmp_path / "subject.edf").exists()
