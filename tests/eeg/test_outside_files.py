"""Files written by other software, and the EEG service's endpoints fed bad input.

Each test was written against a bug found by acting as an outside tool: MNE's own writers
(``raw.save``, ``mne.export.export_raw``), pybv, an XDF writer, damaged copies of their
files, and HTTP/websocket clients sending the wrong types. Recordings are SYNTHETIC
(the virtual subject on an 8-channel cap).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import mne
import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.decoding.eegnet import EEGNet
from services.eeg.recordings.channels import standard_name
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.io import RecordingError, action_events, read_recording
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.signal.preprocessing import PreprocessingParams
from tests.eeg.caps import CAP_8, LABELS, virtual_recording
from tests.eeg.xdf_writer import XdfStream, write_xdf

SFREQ = 500.0
CODES = [1 if ok else 2 for ok in LABELS]


@pytest.fixture(scope="module")
def raw() -> mne.io.RawArray:
    return virtual_recording(SFREQ, CAP_8, seed=4)


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, max_upload_bytes=8 << 20, epoch_wait_s=0.2)
    with TestClient(create_app(settings)) as c:
        yield c


def _codes(recording: mne.io.BaseRaw) -> list[int]:
    return action_events(recording)[:, 2].tolist()


# ----------------------------------------------------------------------------- files


def test_bdf_exported_by_mne_keeps_its_action_codes(raw, tmp_path):
    """``mne.export.export_raw(fmt="bdf")`` scales Status (codes 0..2 over the digital
    range); it used to be read as the raw trigger word: 11 'correct' actions, one at t=0."""
    path = tmp_path / "exported.bdf"
    mne.export.export_raw(path, raw, fmt="bdf", verbose="error")
    back = read_recording(path)
    assert _codes(back) == CODES
    np.testing.assert_array_equal(
        action_events(back)[:, 0] - back.first_samp, action_events(raw)[:, 0] - raw.first_samp
    )


@pytest.mark.parametrize("kept", [0.5, 0.999])
def test_truncated_fif_is_refused_as_truncated(raw, tmp_path, kept):
    """A cut FIF file used to fail deep in MNE with a bare ValueError (a 500 on upload)."""
    whole = tmp_path / "whole_raw.fif"
    raw.save(whole, verbose="error")
    data = whole.read_bytes()
    cut = tmp_path / "cut_raw.fif"
    cut.write_bytes(data[: int(len(data) * kept)])
    with pytest.raises(RecordingError, match=r"^cut_raw\.fif: truncated: a FIF tag at byte"):
        read_recording(cut)


def _pybv_set(raw, folder: Path) -> dict[str, bytes]:
    import pybv

    events = action_events(raw)
    pybv.write_brainvision(
        data=raw.get_data(picks=CAP_8),
        sfreq=SFREQ,
        ch_names=CAP_8,
        fname_base="s01",
        folder_out=folder,
        events=[
            {"onset": int(onset), "description": int(code), "type": "Stimulus"}
            for onset, code in zip(events[:, 0] - raw.first_samp, events[:, 2], strict=True)
        ],
        unit="µV",
    )
    return {suffix: (folder / f"s01.{suffix}").read_bytes() for suffix in ("vhdr", "vmrk", "eeg")}


def _zip(path: Path, members: list[tuple[str, bytes]]) -> Path:
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members:
            archive.writestr(name, data)
    return path


@pytest.fixture(scope="module")
def brainvision(raw, tmp_path_factory) -> dict[str, bytes]:
    return _pybv_set(raw, tmp_path_factory.mktemp("vhdr"))


def test_truncated_brainvision_set_is_refused(brainvision, tmp_path):
    """MNE reads the samples a cut .eeg holds and drops the later markers, silently."""
    vhdr, vmrk, eeg = brainvision["vhdr"], brainvision["vmrk"], brainvision["eeg"]
    frame = 4 * len(CAP_8)  # float32 samples of 8 channels
    mid_sample = _zip(
        tmp_path / "mid.zip", [("s01.vhdr", vhdr), ("s01.vmrk", vmrk), ("s01.eeg", eeg[:-5])]
    )
    with pytest.raises(RecordingError, match=r"truncated: the \.eeg file ends inside a sample"):
        read_recording(mid_sample)
    on_frame = _zip(
        tmp_path / "frame.zip",
        [("s01.vhdr", vhdr), ("s01.vmrk", vmrk), ("s01.eeg", eeg[: frame * 5000])],
    )
    with pytest.raises(RecordingError, match=r"markers up to sample \d+ but the \.eeg holds 5000"):
        read_recording(on_frame)


def test_brainvision_zip_names_are_checked(brainvision, raw, tmp_path):
    vhdr, vmrk, eeg = brainvision["vhdr"], brainvision["vmrk"], brainvision["eeg"]
    # DataFile=.. used to open the extraction folder itself for writing (IsADirectoryError).
    dotdot = vhdr.replace(b"DataFile=s01.eeg", b"DataFile=..")
    bad = _zip(tmp_path / "dotdot.zip", [("s01.vhdr", dotdot), ("s01.vmrk", vmrk), ("x/..", eeg)])
    with pytest.raises(RecordingError, match=r"DataFile='\.\.' names no data or marker file"):
        read_recording(bad)
    # Two markers files of one name in two folders: one was read, whichever came last.
    twice = _zip(
        tmp_path / "twice.zip",
        [("s01.vhdr", vhdr), ("a/s01.vmrk", b"junk"), ("b/s01.vmrk", vmrk), ("s01.eeg", eeg)],
    )
    with pytest.raises(RecordingError, match=r"2 files named s01\.vmrk \(a/s01\.vmrk, b/s01"):
        read_recording(twice)
    # A set written on Windows: upper-case names, accepted like the header names them.
    windows = _zip(
        tmp_path / "windows.zip", [("S01.VHDR", vhdr), ("S01.VMRK", vmrk), ("S01.EEG", eeg)]
    )
    assert _codes(read_recording(windows)) == CODES


def test_zip_without_a_brainvision_set_says_what_it_is(raw, tmp_path):
    fif = tmp_path / "rec_raw.fif"
    raw.save(fif, verbose="error")
    zipped = _zip(tmp_path / "rec.zip", [("rec_raw.fif", fif.read_bytes())])
    not_brainvision = (
        r"^rec\.zip: not a readable .* file: a zip without a BrainVision \.vhdr or an EEGLAB \.set"
    )
    with pytest.raises(RecordingError, match=not_brainvision):
        read_recording(zipped)
    cut = tmp_path / "cut.zip"
    cut.write_bytes(zipped.read_bytes()[:200])
    damaged = r"^cut\.zip: not a readable .* file: a damaged or truncated zip"
    with pytest.raises(RecordingError, match=damaged):
        read_recording(cut)


def test_samples_not_in_volts_are_refused(raw, tmp_path):
    """Microvolts stored as volts (std ~30 V) used to be accepted and calibrated on."""
    in_microvolts = raw.copy()
    in_microvolts.apply_function(lambda x: x * 1e6, picks=CAP_8)
    path = tmp_path / "uv_raw.fif"
    in_microvolts.save(path, verbose="error")
    with pytest.raises(RecordingError, match=r"standard deviation over 1 V in Fz \(\d+\.?\d* V\)"):
        read_recording(path)


def _xdf(raw, path: Path, *, units: str = "microvolts", nominal: float = SFREQ) -> Path:
    times = 5021.25 + np.arange(raw.n_times) / SFREQ
    events = action_events(raw)
    eeg = XdfStream(
        "amp",
        "EEG",
        times,
        raw.get_data(picks=CAP_8).T * 1e6,
        nominal,
        [{"label": ch, "unit": units} for ch in CAP_8],
    )
    markers = XdfStream(
        "BrainNav-Markers",
        "Markers",
        times[events[:, 0] - raw.first_samp],
        ["correct" if code == 1 else "error" for code in events[:, 2]],
    )
    return write_xdf(path, [eeg, markers])


def test_xdf_units_and_rate_are_checked(raw, tmp_path):
    assert _codes(read_recording(_xdf(raw, tmp_path / "ok.xdf"))) == CODES
    # An unknown unit ("counts") left the microvolt numbers as volts.
    with pytest.raises(RecordingError, match=r"the samples are not in volts"):
        read_recording(_xdf(raw, tmp_path / "counts.xdf", units="counts"))
    # A nominal rate the timestamps contradict (500 Hz samples declared 512 Hz) was taken.
    with pytest.raises(RecordingError, match=r"declares 512 Hz but its timestamps give 500 Hz"):
        read_recording(_xdf(raw, tmp_path / "rate.xdf", nominal=512.0))


def test_edf_plus_labels_are_standard_names(raw, tmp_path):
    """EDF+ labels (``EEG Fz-REF``) and an upper-case ``STATUS`` used to be refused."""
    clinical = raw.copy()
    clinical.rename_channels({ch: f"EEG {ch.upper()}-REF" for ch in CAP_8} | {"Status": "STATUS"})
    path = tmp_path / "clinical.edf"
    mne.export.export_raw(path, clinical, fmt="edf", verbose="error")
    back = read_recording(path)
    assert back.ch_names[: len(CAP_8)] == CAP_8 and STIM_CHANNEL in back.ch_names
    assert _codes(back) == CODES
    assert standard_name("Fz-Cz") is None  # a bipolar derivation is not the site Fz
    assert standard_name("EEG Cz-Avg") == "Cz"


# ----------------------------------------------------------------------------- service


def test_upload_of_a_truncated_fif_is_a_422_and_keeps_what_is_stored(raw, tmp_path, client):
    good = tmp_path / "good_raw.fif"
    raw.save(good, verbose="error")
    stored = client.post("/recordings", params={"filename": "good.fif"}, content=good.read_bytes())
    assert stored.status_code == 201, stored.text
    cut = good.read_bytes()[: good.stat().st_size * 9 // 10]
    response = client.post("/recordings", params={"filename": "cut.fif"}, content=cut)
    assert response.status_code == 422, response.text
    assert response.json()["detail"].startswith("cut.fif: truncated: a FIF tag at byte")
    assert [r["id"] for r in client.get("/recordings").json()] == [stored.json()["id"]]


def _save_classifier(client: TestClient, classifier_id: str) -> ErrPClassifier:
    params = PreprocessingParams()
    model = EEGNet(len(CAP_8), 2, params.n_times_epoch)
    clf = ErrPClassifier(model, params, CAP_8, SFREQ, 1e5)
    clf.save(client.app.state.service.settings.eeg_dir / "classifiers" / classifier_id)
    return clf


def test_classify_refuses_samples_that_are_not_numbers(client):
    clf = _save_classifier(client, "clf1")
    n_ch, n_times = clf.epoch_shape
    url = "/classifiers/clf1/classify"
    body = {"epoch": np.zeros((n_ch, n_times)).tolist(), "ch_names": CAP_8, "sfreq": 128.0}
    assert client.post(url, json=body).status_code == 200
    # JSON false/true and "0" used to be read as 0.0/1.0: a classified epoch of booleans.
    for value in (False, "0"):
        response = client.post(url, json={**body, "epoch": [[value] * n_times] * n_ch})
        assert response.status_code == 422, response.text
        assert response.json()["detail"][0]["field"] == "epoch.0.0"


@pytest.mark.parametrize(("field", "value"), [("seed", "1"), ("max_passes", True)])
def test_job_numbers_must_be_json_integers(client, field, value):
    """``"seed": "1"`` and ``"max_passes": true`` used to be taken as 1."""
    response = client.post("/jobs", json={"recording_id": "ab" * 32, field: value})
    assert response.status_code == 422, response.text
    assert response.json()["detail"][0]["field"] == field


def test_ingest_chunk_with_ragged_rows_names_the_row(client):
    names = [*CAP_8, STIM_CHANNEL]
    with client.websocket_connect("/live/ingest") as ws:
        ws.send_json({"ch_names": names, "sfreq": SFREQ})
        assert ws.receive_json()["ok"] is True
        ws.send_json({"first_timestamp": 1.0, "samples": [[0.0] * 9, [0.0] * 8]})
        assert ws.receive_json() == {
            "ok": False,
            "error": "samples: each row holds one value per channel (9); row 1 holds 8",
        }
        ws.send_json({"first_timestamp": 1.0, "samples": [[True] * 9]})
        reply = ws.receive_json()
        assert reply["ok"] is False and reply["error"].startswith("samples.0.0:")


def test_one_damaged_item_does_not_hide_the_others(client):
    """One unloadable classifier made GET /classifiers a 409; one unreadable recording
    record made GET /recordings a 500."""
    _save_classifier(client, "good")
    eeg_dir = client.app.state.service.settings.eeg_dir
    broken = eeg_dir / "classifiers" / "broken"
    broken.mkdir()
    (broken / "classifier.json").write_text("{not json")
    assert [c["id"] for c in client.get("/classifiers").json()] == ["good"]
    assert client.get("/classifiers/broken").status_code == 409
    (eeg_dir / "recordings" / f"{'0' * 64}.json").write_text(json.dumps({"id": "x"}))
    response = client.get("/recordings")
    assert response.status_code == 200 and response.json() == []
