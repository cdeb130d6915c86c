"""BDF writing and validated reading of recordings."""

from __future__ import annotations

import datetime
import hashlib
import logging

import mne
import numpy as np
import pytest

from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.io import (
    RecordingError,
    action_events,
    detect_format,
    file_sha256,
    format_mismatch,
    is_synthetic,
    read_recording,
    validate_recording,
    write_bdf,
)
from services.eeg.virtual.subject import SyntheticRecording, simulate_recording

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
    with pytest.raises(
        RecordingError,
        match=r"junk\.bdf: not a readable BDF, EDF, FIF, BrainVision, EEGLAB or XDF file",
    ):
        read_recording(tmp_path / "junk.bdf")

    with pytest.raises(RecordingError, match=r"sampling rate 100 Hz is outside 128-20000 Hz"):
        read_recording(_save(raw.copy().resample(100.0, verbose="error"), tmp_path))
    with pytest.raises(
        RecordingError,
        match=r"missing the fronto-central sites the ErrP is decoded from: Cz \(required",
    ):
        read_recording(_save(raw.copy().drop_channels(["Cz"]), tmp_path))
    with pytest.raises(RecordingError, match=r"1 of 2 required EEG channels missing \(Iz\)"):
        read_recording(_save(raw.copy().drop_channels(["Iz"]), tmp_path), ch_names=["Cz", "Iz"])
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
    with pytest.raises(RecordingError, match="no action events"):
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


MEAS_DATE = datetime.datetime(2026, 11, 1, 12, 30, 5, tzinfo=datetime.UTC)


def test_format_comes_from_the_header_not_the_name(raw, tmp_path, caplog):
    """A BDF named .edf is read as BDF (it used to yield fake actions) and the mismatch is told."""
    bdf = write_bdf(raw, tmp_path / "rec.bdf")
    misnamed = bdf.rename(tmp_path / "rec.edf")
    assert detect_format(misnamed) == "bdf"
    with caplog.at_level(logging.WARNING, logger="services.eeg.recordings.io"):
        back = read_recording(misnamed)
    note = "rec.edf: the file's header says BDF, not EDF; it is read as BDF"
    assert caplog.messages == [note]
    assert format_mismatch("rec.edf", "bdf") == note
    assert format_mismatch("rec.bdf", "bdf") is None
    np.testing.assert_array_equal(action_events(back), action_events(raw))
    fif = tmp_path / "rec_raw.fif"
    raw.save(fif, verbose="error")
    assert detect_format(fif) == "fif"
    assert detect_format(fif.rename(tmp_path / "rec.bdf")) == "fif"
    assert len(action_events(read_recording(tmp_path / "rec.bdf"))) == len(LABELS)


def test_truncated_bdf_is_refused_with_the_reason(raw, tmp_path):
    path = write_bdf(raw, tmp_path / "rec.bdf")
    data = path.read_bytes()
    header = 256 * (len(raw.ch_names) + 1)
    record = len(raw.ch_names) * int(SFREQ) * 3  # 1 s records of 24-bit samples
    assert len(data) == header + 16 * record
    cut = tmp_path / "cut.bdf"
    cut.write_bytes(data[: header + 5 * record + record // 2])
    with pytest.raises(RecordingError) as info:
        read_recording(cut)
    assert str(info.value) == (
        "cut.bdf: truncated: the header declares 16 data records (16 s) but the file holds "
        f"5 complete records (5 s); {10 * record + record // 2} bytes are missing (was the "
        "copy or upload cut short?)"
    )
    cut.write_bytes(data + b"\0" * 10)
    with pytest.raises(RecordingError, match="10 bytes follow the 16 data records"):
        read_recording(cut)


def test_error_messages_name_the_file_never_its_folder(raw, tmp_path):
    """A broken FIF's message used to show the server's path; it names the upload only."""
    good = tmp_path / "good_raw.fif"
    raw.save(good, verbose="error")
    stored = tmp_path / "store" / ".upload-x1y2.fif"
    stored.parent.mkdir()
    stored.write_bytes(good.read_bytes()[:36] + b"\0" * 64)  # a FIF file-id tag, then junk
    with pytest.raises(RecordingError) as info:
        read_recording(stored, name="my session.fif")
    message = str(info.value)
    assert message == (
        "my session.fif: not a readable FIF file (file my session.fif does not have a "
        "directory pointer)"
    )
    assert str(tmp_path) not in message and "upload" not in message
    with pytest.raises(RecordingError, match=r"^gone\.bdf: no such file$"):
        read_recording(tmp_path / "nowhere" / "x.bdf", name="/client/dir/gone.bdf")


def test_generator_blocks_equal_the_recording_and_the_previous_generator(tmp_path):
    """Block-wise generation gives the samples of the one-shot generator (pinned figures,
    to a tolerance: the exact float32 bits depend on the CPU's FFT kernels), and the chunked
    BDF writer stores them within one 24-bit step."""
    labels = (np.random.default_rng(0).random(90) < 0.7).tolist()
    recording = SyntheticRecording(labels, quality=0.7, seed=3)
    assert recording.n_times == 284672  # two generation blocks of 2**18 samples
    blocks = [block for _, block in recording.iter_chunks()]
    assert [b.dtype for b in blocks] == [np.float32, np.float32]
    data = np.concatenate(blocks, axis=1)
    wide = data.astype(np.float64)
    np.testing.assert_allclose(
        wide.std(axis=1)[:4],
        [2.33076984e-05, 2.55548247e-05, 2.12476264e-05, 3.79030867e-05],
        rtol=1e-4,
    )
    np.testing.assert_allclose(
        wide[:3, 1000], [-2.06870463e-05, 6.07477159e-06, -2.47621392e-06], rtol=1e-4
    )
    np.testing.assert_allclose(np.abs(wide).sum(), 2801.1491654075794, rtol=1e-4)
    recording.info.set_meas_date(MEAS_DATE)
    raw = recording.to_raw()
    np.testing.assert_array_equal(raw.get_data(), data)  # a second pass: the same samples
    written = write_bdf(recording, tmp_path / "generated.bdf")
    back = mne.io.read_raw_bdf(written, preload=True, verbose="error")
    eeg = [name != STIM_CHANNEL for name in back.ch_names]
    step = np.ptp(wide[eeg], axis=1, keepdims=True) / 2**23
    assert np.all(np.abs(back.get_data()[eeg] - wide[eeg]) <= step)
    np.testing.assert_array_equal(action_events(back), action_events(raw))


def test_flat_check_is_exact_under_a_large_dc_offset(raw):
    """Chunked validation keeps a 30 mV offset from hiding (or faking) a flat channel."""
    shifted = raw.copy()
    rng = np.random.default_rng(0)
    k = shifted.ch_names.index("Cz")
    shifted._data[k] = 0.03 + 2e-9 * rng.standard_normal(shifted.n_times)
    validate_recording(shifted)  # 2 nV noise on 30 mV: not flat
    shifted._data[k] = 0.03 + 0.5e-9 * rng.standard_normal(shifted.n_times)
    with pytest.raises(RecordingError, match=r"flat channels \(std < 1 nV\): Cz"):
        validate_recording(shifted, name="x")


@pytest.mark.parametrize(
    ("sfreq", "cap"),
    [(250.0, "8"), (500.0, "32"), (1000.0, "8"), (2048.0, "64"), (500.0, "8")],
)
def test_any_cap_and_rate_is_read_and_epoched(sfreq, cap, tmp_path):
    """An OpenBCI-like 250 Hz, BrainAmp-like 500/1000 Hz and BioSemi 2048 Hz recording."""
    from services.eeg.recordings.epochs import epochs_from_raw
    from tests.eeg.caps import CAP_8, CAP_32, CAP_64, LABELS, virtual_recording

    names = {"8": CAP_8, "32": CAP_32, "64": CAP_64}[cap]
    raw = virtual_recording(sfreq, names, seed=5)
    path = write_bdf(raw, tmp_path / "rec.bdf")
    back = read_recording(path)
    assert back.info["sfreq"] == sfreq
    assert back.ch_names == [*names, STIM_CHANNEL]
    assert back.get_channel_types() == ["eeg"] * len(names) + ["stim"]
    epochs = epochs_from_raw(back)
    assert epochs.X.shape == (len(LABELS), len(names), 103)
    assert epochs.ch_names == names
    assert epochs.sfreq_in == sfreq
    np.testing.assert_array_equal(epochs.y, [0 if ok else 1 for ok in LABELS])


def test_device_names_and_other_channels_through_a_rig_map(tmp_path):
    """ActiView's A1..B32 names read through the rig's map; EXG kept but not decoded."""
    from services.eeg.recordings.channels import builtin_channel_map
    from tests.eeg.caps import CAP_64, virtual_recording

    raw = virtual_recording(512.0, CAP_64, seed=6)
    mapping = builtin_channel_map("biosemi64")
    raw.rename_channels({std: dev for dev, std in mapping.items()})
    exg = mne.io.RawArray(
        np.random.default_rng(0).standard_normal((1, raw.n_times)) * 1e-5,
        mne.create_info(["EXG1"], 512.0, ["eeg"]),
        verbose="error",
    )
    raw.add_channels([exg], force_update_info=True)
    path = write_bdf(raw, tmp_path / "actiview.bdf")
    # only A1 and A2 read as standard names (the ear lobes): without the map it is refused
    with pytest.raises(RecordingError, match=r"2 channels with standard 10-20/10-10 names"):
        read_recording(path)
    back = read_recording(path, channel_map=mapping)
    assert back.ch_names == [*CAP_64, STIM_CHANNEL, "EXG1"]
    assert back.get_channel_types() == ["eeg"] * 64 + ["stim", "misc"]
    with pytest.raises(RecordingError, match=r"the channel map names channels .*: A65"):
        read_recording(path, channel_map={**mapping, "A65": "Iz"})
