"""Files as labs have them: BrainVision, XDF, EDF+ annotations, mapped event labels.

Every file is written by its format's own writer (pybv, mne.export, the XDF writer of
tests/eeg/xdf_writer.py) from a SYNTHETIC virtual-subject recording and read back.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import mne
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.core.markers import ActionMarker
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.formats import EventLabels
from services.eeg.recordings.io import RecordingError, action_events, detect_format, read_recording
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from tests.eeg.caps import CAP_8, LABELS, virtual_recording
from tests.eeg.xdf_writer import XdfStream, write_xdf

SFREQ = 500.0
CODES = [1 if ok else 2 for ok in LABELS]


@pytest.fixture(scope="module")
def raw() -> mne.io.RawArray:
    return virtual_recording(SFREQ, CAP_8, seed=4)


def action_samples(raw: mne.io.BaseRaw) -> np.ndarray:
    return action_events(raw)[:, 0] - raw.first_samp


def write_vhdr(raw, folder: Path, events: list[dict], name: str = "sub01") -> Path:
    import pybv

    pybv.write_brainvision(
        data=raw.get_data(picks=CAP_8),
        sfreq=raw.info["sfreq"],
        ch_names=CAP_8,
        fname_base=name,
        folder_out=folder,
        events=events,
        unit="µV",
    )
    return folder / f"{name}.vhdr"


def zip_files(files: list[Path], path: Path) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for file in files:
            archive.write(file, f"export/{file.name}")
    return path


def test_brainvision_stimulus_codes_from_vhdr_and_zip(raw, tmp_path):
    onsets = action_samples(raw)
    events = [{"onset": int(s), "description": c} for s, c in zip(onsets, CODES, strict=True)]
    vhdr = write_vhdr(raw, tmp_path, events)
    assert detect_format(vhdr) == "brainvision"
    back = read_recording(vhdr)
    np.testing.assert_array_equal(action_samples(back), onsets)
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)
    assert back.ch_names == [*CAP_8, STIM_CHANNEL]
    assert back.get_channel_types() == ["eeg"] * 8 + ["stim"]
    np.testing.assert_allclose(back.get_data(picks=CAP_8), raw.get_data(picks=CAP_8), atol=1e-7)

    archive = zip_files(sorted(tmp_path.glob("sub01.*")), tmp_path / "sub01.zip")
    assert detect_format(archive) == "brainvision"
    zipped = read_recording(archive)
    np.testing.assert_array_equal(zipped.get_data(), back.get_data())


def test_brainvision_comment_annotations_and_a_lab_mapping(raw, tmp_path):
    onsets = action_samples(raw)
    texts = ["hit" if ok else "miss" for ok in LABELS]
    events = [
        {"onset": int(s), "description": t, "type": "Comment"}
        for s, t in zip(onsets, texts, strict=True)
    ]
    vhdr = write_vhdr(raw, tmp_path, events)
    with pytest.raises(RecordingError, match="no 'Status' trigger channel, and no annotation"):
        read_recording(vhdr)
    labels = EventLabels(descriptions={"HIT": "correct", "miss": "error"})
    back = read_recording(vhdr, labels=labels)
    np.testing.assert_array_equal(action_samples(back), onsets)
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)


def test_brainvision_sets_missing_files_are_refused(raw, tmp_path):
    vhdr = write_vhdr(raw, tmp_path, [{"onset": 10, "description": 1}])
    (tmp_path / "sub01.eeg").unlink()
    with pytest.raises(
        RecordingError,
        match=r"^sub01\.vhdr: the header refers to sub01\.eeg, not found beside it",
    ):
        read_recording(vhdr)
    lone = zip_files([vhdr, tmp_path / "sub01.vmrk"], tmp_path / "lone.zip")
    with pytest.raises(RecordingError, match=r"^lone\.zip: the zip lacks sub01\.eeg"):
        read_recording(lone)
    empty = tmp_path / "other.zip"
    with zipfile.ZipFile(empty, "w") as archive:
        archive.writestr("notes.txt", "hello")
    with pytest.raises(
        RecordingError, match="not a readable BDF, EDF, FIF, BrainVision, EEGLAB or XDF"
    ):
        read_recording(empty)


def write_set(raw, path: Path, *, fdt: bool = False) -> Path:
    """An EEGLAB dataset as ``mne.export`` (eeglabio) writes it: samples inside the .set; with
    ``fdt``, as EEGLAB saves by default: the samples (float32, channels x samples,
    column-major) in a .fdt the .set names."""
    import scipy.io

    plain = raw.copy().pick(CAP_8)
    onsets = action_samples(raw)
    plain.set_annotations(mne.Annotations(onsets / SFREQ, 0.0, [str(c) for c in CODES]))
    mne.export.export_raw(path, plain, fmt="eeglab", overwrite=True, verbose="error")
    if fdt:
        fields = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
        samples = path.with_suffix(".fdt")
        np.asarray(fields["data"], dtype="<f4").T.tofile(samples)
        fields["data"] = fields["datfile"] = samples.name
        scipy.io.savemat(path, fields)
    return path


def test_eeglab_datasets_with_and_without_fdt_and_zipped(raw, tmp_path):
    inside = write_set(raw, tmp_path / "inside.set")
    assert inside.read_bytes().startswith(b"MATLAB 5.0 MAT-file")
    assert detect_format(inside) == "eeglab"
    back = read_recording(inside)
    np.testing.assert_array_equal(action_samples(back), action_samples(raw))
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)
    assert back.ch_names == [*CAP_8, STIM_CHANNEL]
    np.testing.assert_allclose(back.get_data(picks=CAP_8), raw.get_data(picks=CAP_8), atol=1e-9)

    (tmp_path / "split").mkdir()
    split = write_set(raw, tmp_path / "split" / "sub02.set", fdt=True)
    assert len(split.read_bytes()) < 10_000  # the samples are in the .fdt
    np.testing.assert_array_equal(read_recording(split).get_data(), back.get_data())
    archive = zip_files([split, split.with_suffix(".fdt")], tmp_path / "sub02.zip")
    assert detect_format(archive) == "eeglab"
    np.testing.assert_array_equal(read_recording(archive).get_data(), back.get_data())


def test_eeglab_datasets_that_cannot_be_used_are_refused_by_name(raw, tmp_path):
    split = write_set(raw, tmp_path / "sub03.set", fdt=True)
    samples = split.with_suffix(".fdt")
    lone = zip_files([split], tmp_path / "lone.zip")
    with pytest.raises(
        RecordingError,
        match=r"^lone\.zip: the dataset keeps its samples in "
        r"sub03\.fdt, not found beside it \(keep the \.set and \.fdt together",
    ):
        read_recording(lone)
    two = zip_files([split, samples, write_set(raw, tmp_path / "other.set")], tmp_path / "two.zip")
    with pytest.raises(RecordingError, match=r"^two\.zip: an EEGLAB zip holds one \.set"):
        read_recording(two)
    samples.write_bytes(samples.read_bytes()[:-100])
    with pytest.raises(RecordingError, match=r"^sub03\.set: truncated: the \.fdt holds fewer"):
        read_recording(split)

    plain = raw.copy().pick(CAP_8)
    events = np.column_stack([action_samples(raw)[:5], np.zeros(5, int), np.ones(5, int)])
    epochs = mne.Epochs(plain, events, tmin=0, tmax=0.5, baseline=None, verbose="error")
    epoched = tmp_path / "epochs.set"
    epochs.export(epoched, fmt="eeglab", verbose="error")
    with pytest.raises(
        RecordingError,
        match=r"^epochs\.set: not a readable EEGLAB dataset "
        r"\(an epoched dataset; export the continuous recording\)",
    ):
        read_recording(epoched)

    import scipy.io

    other = tmp_path / "weights.set"
    scipy.io.savemat(other, {"weights": np.ones((3, 3))})
    with pytest.raises(RecordingError, match=r"^weights\.set: not a readable EEGLAB dataset"):
        read_recording(other)


def test_edf_plus_annotations_become_actions(raw, tmp_path):
    plain = raw.copy().drop_channels([STIM_CHANNEL])
    onsets = action_samples(raw)
    plain.set_annotations(
        mne.Annotations(
            onsets / SFREQ, [0.0] * len(onsets), ["correct" if ok else "error" for ok in LABELS]
        )
    )
    path = tmp_path / "annotated.edf"
    mne.export.export_raw(path, plain, fmt="edf", verbose="error")
    back = read_recording(path)
    np.testing.assert_array_equal(action_samples(back), onsets)
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)


def test_an_edf_clipped_by_a_physical_range_in_the_wrong_unit_is_refused(raw, tmp_path):
    """mne.export takes the range in the data's unit (µV): (-2e-3, 2e-3) meant as volts leaves
    every sample at a digital extreme, +-2 nV, which passed as EEG before."""
    plain = raw.copy().pick(CAP_8)
    plain.set_annotations(
        mne.Annotations(action_samples(raw) / SFREQ, 0.0, [str(c) for c in CODES])
    )
    path = tmp_path / "clipped.edf"
    mne.export.export_raw(path, plain, fmt="edf", physical_range=(-2e-3, 2e-3), verbose="error")
    with pytest.raises(
        RecordingError,
        match=r"^clipped\.edf: clipped channels, at most 4 "
        r"distinct sample values in their first 10 s: Fz, FC1, .* wrong unit\?\)",
    ):
        read_recording(path)


def test_status_codes_by_a_lab_mapping(raw, tmp_path):
    from services.eeg.recordings.io import write_bdf

    relabelled = raw.copy()
    status = relabelled._data[-1]
    relabelled._data[-1] = np.select([status == 1, status == 2], [11, 12], 0)
    path = write_bdf(relabelled, tmp_path / "codes.bdf")
    with pytest.raises(RecordingError, match="no action events"):
        read_recording(path)
    back = read_recording(path, labels=EventLabels(codes={11: "correct", 12: "error"}))
    np.testing.assert_array_equal(action_samples(back), action_samples(raw))
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)


def xdf_recording(
    raw, path: Path, markers: list[str], *, t0: float = 5021.25, extra: list | None = None
):
    n = raw.n_times
    eeg = XdfStream(
        "actiCHamp-1",
        "EEG",
        t0 + np.arange(n) / SFREQ,
        raw.get_data(picks=CAP_8).T * 1e6,
        SFREQ,
        [{"label": ch.upper(), "unit": "microvolts", "type": "EEG"} for ch in CAP_8],
    )
    onsets = action_samples(raw)
    stream = XdfStream("BrainNav-Markers", "Markers", t0 + onsets / SFREQ + 0.0004, markers)
    return write_xdf(path, [eeg, stream, *(extra or [])])


def test_xdf_eeg_and_marker_streams(raw, tmp_path):
    action_markers = [
        ActionMarker(
            session_id="s1", episode=0, step=i, action=0, correct=ok, timestamp=0.0
        ).to_lsl()
        for i, ok in enumerate(LABELS)
    ]
    path = xdf_recording(raw, tmp_path / "session.xdf", action_markers)
    assert detect_format(path) == "xdf"
    back = read_recording(path)
    assert back.ch_names == [*CAP_8, STIM_CHANNEL]
    assert back.info["sfreq"] == SFREQ
    np.testing.assert_array_equal(action_samples(back), action_samples(raw))
    np.testing.assert_array_equal(action_events(back)[:, 2], CODES)
    np.testing.assert_allclose(back.get_data(picks=CAP_8), raw.get_data(picks=CAP_8), atol=1e-10)

    texts = tmp_path / "texts.xdf"
    xdf_recording(raw, texts, ["correct" if ok else "error" for ok in LABELS])
    np.testing.assert_array_equal(action_events(read_recording(texts))[:, 2], CODES)


def test_xdf_stream_choice_by_name(raw, tmp_path):
    other = XdfStream("Keyboard", "Markers", np.array([5022.0]), ["space"])
    path = xdf_recording(raw, tmp_path / "two.xdf", ["correct"] * len(LABELS), extra=[other])
    with pytest.raises(
        RecordingError,
        match=r"two\.xdf: 2 streams of type 'markers'; name the marker stream \(streams: "
        r"'BrainNav-Markers' \(type Markers\), 'Keyboard' \(type Markers\)\)",
    ):
        read_recording(path)
    back = read_recording(path, xdf_marker_stream="BrainNav-Markers", xdf_stream="actiCHamp-1")
    assert len(action_events(back)) == len(LABELS)
    with pytest.raises(RecordingError, match=r"no EEG stream named 'BioSemi'; it has"):
        read_recording(path, xdf_stream="BioSemi", xdf_marker_stream="BrainNav-Markers")


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path / "data", max_upload_bytes=50 << 20)
    with TestClient(create_app(settings)) as c:
        yield c


def test_upload_route_takes_brainvision_zips_and_xdf(raw, tmp_path, client):
    onsets = action_samples(raw)
    events = [{"onset": int(s), "description": c} for s, c in zip(onsets, CODES, strict=True)]
    vhdr = write_vhdr(raw, tmp_path, events)
    archive = zip_files(sorted(tmp_path.glob("sub01.*")), tmp_path / "sub01.zip")
    response = client.post("/recordings", files={"file": ("sub01.zip", archive.read_bytes())})
    assert response.status_code == 201, response.text
    body = response.json()
    assert (body["format"], body["n_channels"], body["sfreq"]) == ("brainvision", 9, SFREQ)
    assert (body["n_actions"], body["n_errors"]) == (len(LABELS), CODES.count(2))

    lone = client.post("/recordings", files={"file": ("sub01.vhdr", vhdr.read_bytes())})
    assert lone.status_code == 422
    assert lone.json()["detail"] == (
        "sub01.vhdr: the header refers to sub01.eeg and sub01.vmrk, not found beside it "
        "(keep the .vhdr, .vmrk and .eeg together; upload them as one zip)"
    )

    xdf = xdf_recording(
        raw, tmp_path / "session.xdf", ["correct" if ok else "error" for ok in LABELS]
    )
    response = client.post(
        "/recordings", params={"filename": "session.xdf"}, content=xdf.read_bytes()
    )
    assert response.status_code == 201, response.text
    assert (response.json()["format"], response.json()["n_actions"]) == ("xdf", len(LABELS))
    stored = sorted((tmp_path / "data").rglob("*.brainvision"))
    assert len(stored) == 1
    assert len(action_events(read_recording(stored[0]))) == len(LABELS)


def test_upload_route_takes_eeglab_sets_and_zips(raw, tmp_path, client):
    inside = write_set(raw, tmp_path / "inside.set")
    response = client.post("/recordings", files={"file": ("inside.set", inside.read_bytes())})
    assert response.status_code == 201, response.text
    body = response.json()
    assert (body["format"], body["n_channels"], body["sfreq"]) == ("eeglab", 9, SFREQ)
    assert (body["n_actions"], body["n_errors"]) == (len(LABELS), CODES.count(2))

    (tmp_path / "split").mkdir()
    split = write_set(raw, tmp_path / "split" / "sub04.set", fdt=True)
    lone = client.post("/recordings", files={"file": ("sub04.set", split.read_bytes())})
    assert lone.status_code == 422
    assert "keeps its samples in sub04.fdt" in lone.json()["detail"]
    archive = zip_files([split, split.with_suffix(".fdt")], tmp_path / "sub04.zip")
    response = client.post("/recordings", files={"file": ("sub04.zip", archive.read_bytes())})
    assert response.status_code == 201, response.text
    assert (response.json()["format"], response.json()["n_actions"]) == ("eeglab", len(LABELS))
    stored = sorted((tmp_path / "data").rglob("*.eeglab"))
    assert len(stored) == 2
    for path in stored:
        assert len(action_events(read_recording(path))) == len(LABELS)
