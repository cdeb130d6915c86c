"""Live recording: the live stream and its markers written incrementally, finalised to a
BDF that reads back with the same samples (within 24-bit quantisation) and events; a crash
leaves everything up to the last flushed block recoverable, through the service too."""

from __future__ import annotations

import datetime

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.core.markers import ActionMarker
from services.eeg.live.recording import (
    INDEX_FILE,
    SAMPLES_FILE,
    STORED_FILE,
    LiveRecorder,
    read_log,
    write_bdf_from_log,
)
from services.eeg.recordings.io import action_events, file_sha256, read_recording
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.service.state import EEGService
from services.eeg.virtual.ingest import VirtualIngestClient
from services.eeg.virtual.source import VirtualEEGSource
from services.eeg.virtual.subject import eeg_channel_names
from tests.eeg.test_virtual_source import EEG, AsgiConnection

SFREQ = 256.0
DURATION_S = 20.0
LABELS = [False, True, True, None, False, True, False, True, True, False, True, True]


def _markers(t0: float = 1.0) -> list[ActionMarker]:
    return [
        ActionMarker(
            session_id="rec", step=i, episode=0, action=i % 3, correct=label, timestamp=t0 + 1.5 * i
        )
        for i, label in enumerate(LABELS)
    ]


def _expected(markers: list[ActionMarker], seconds: float, **kwargs) -> np.ndarray:
    """The samples the virtual subject generates for these markers (it is deterministic)."""
    source = VirtualEEGSource(quality=0.5, seed=9, sfreq=SFREQ, **kwargs)
    for marker in markers:
        source.add_marker(marker)
    return source.generate_until(seconds)[0]


def _assert_same_samples(raw, expected: np.ndarray, ch_names: list[str]) -> None:
    """EEG equal within the 24-bit quantisation of each channel's physical range."""
    data = raw.get_data(picks=ch_names)  # volts
    want = expected[:, : len(ch_names)].T.astype(np.float64)
    assert data.shape == want.shape
    step = (want.max(axis=1) - want.min(axis=1)) / (2**24 - 1)
    assert np.all(np.abs(data - want) <= step[:, None] * 0.51 + 1e-12)


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(EEGSettings(data_dir=tmp_path))) as c:
        yield c


def test_twenty_seconds_of_accelerated_virtual_eeg_recorded_and_read_back(client):
    markers = _markers()
    source = VirtualEEGSource(quality=0.5, seed=9, sfreq=SFREQ)
    assert client.post("/live/recording", json={"name": "cal-1"}).status_code == 409  # no source
    with client.websocket_connect("/live/ingest") as ws:  # no classifier: recording only
        ingest = VirtualIngestClient(source, AsgiConnection(ws))
        response = client.post("/live/recording", json={"name": "cal-1"})
        assert response.status_code == 201, response.text
        assert response.json()["synthetic"] is True
        assert client.post("/live/recording", json={"name": "other"}).status_code == 409
        for marker in markers:
            ingest.push_epoch(marker)
            feedback = client.post("/live/markers", json=marker.model_dump(mode="json")).json()
            assert feedback["status"] == "rejected"
            assert feedback["classifier_id"] is None
            assert feedback["reason"].startswith("no classifier")
        ingest.push_until(DURATION_S)
        status = client.get("/live").json()["recording"]
        assert status["name"] == "cal-1"
        assert status["n_markers"] == len(markers)
        assert status["n_samples"] == DURATION_S * SFREQ
        response = client.delete("/live/recording")
    assert response.status_code == 200, response.text
    meta = response.json()
    labelled = [m for m in markers if m.correct is not None]
    assert meta["format"] == "bdf"
    assert meta["filename"] == "cal-1.bdf"
    assert meta["synthetic"] is True
    assert meta["n_actions"] == len(labelled)
    assert meta["n_errors"] == sum(m.correct is False for m in labelled)
    assert meta["duration_s"] == DURATION_S
    assert meta["n_channels"] == 65
    assert meta["notes"] == []
    assert client.get(f"/recordings/{meta['id']}").json() == meta
    assert client.get("/live").json()["recording"] is None
    assert client.get("/live").json()["unfinished_recordings"] == []

    path = client.app.state.service.recordings.file(meta["id"])
    raw = read_recording(path, preload=True)
    assert raw.info["description"].startswith("SYNTHETIC")
    events = action_events(raw)
    assert events[:, 0].tolist() == [round(m.timestamp * SFREQ) for m in labelled]
    assert events[:, 2].tolist() == [m.trigger for m in labelled]
    _assert_same_samples(raw, _expected(markers, DURATION_S), eeg_channel_names())


def test_a_crash_leaves_everything_up_to_the_last_flushed_block_recoverable(tmp_path):
    channels = EEG
    folder = tmp_path / "eeg" / "live_recordings" / "crashed"
    markers = _markers()[:4]  # onsets 1.0 .. 5.5 s
    source = VirtualEEGSource(quality=0.5, seed=9, sfreq=SFREQ, channels=channels)
    for marker in markers:
        source.add_marker(marker)
    recorder = LiveRecorder(
        folder, name="crashed", ch_names=source.ch_names, sfreq=SFREQ, synthetic=True
    )
    for k in range(26):  # 6.5 s in 0.25 s chunks: 6 blocks of 1 s flushed, 0.5 s buffered
        samples, first = source.generate_until((k + 1) * 0.25)
        recorder.add_samples(samples, first + np.arange(len(samples)) / SFREQ)
        if k == 4:
            for marker in markers:
                recorder.add_marker(marker)
    # The crash: the recorder is dropped without closing, in the middle of writing a block.
    del recorder
    with (folder / SAMPLES_FILE).open("ab") as fh:
        fh.write(b"\x00" * 1000)  # samples of a block whose index lines never came
    with (folder / INDEX_FILE).open("ab") as fh:
        fh.write(b'{"kind": "run", "start": 1536, "n"')  # cut mid-line

    log = read_log(folder)
    assert log.n_samples == 6 * SFREQ
    assert len(log.runs) == 1
    assert len(log.markers) == 4
    assert log.synthetic is True
    finalised = write_bdf_from_log(log, tmp_path / "crashed.bdf")
    raw = read_recording(finalised.path, preload=True, ch_names=channels)
    # The header starts when the recording did, so finalising again gives the same file.
    assert raw.info["meas_date"] == datetime.datetime.fromisoformat(log.started_at)
    again = write_bdf_from_log(log, tmp_path / "again.bdf")
    assert file_sha256(again.path) == file_sha256(finalised.path)
    _assert_same_samples(raw, _expected(markers, 6.0, channels=channels), channels)
    labelled = [m for m in markers if m.correct is not None]
    assert action_events(raw)[:, 0].tolist() == [round(m.timestamp * SFREQ) for m in labelled]

    # Through the service after a restart: listed as unfinished, finalised on request.
    with TestClient(create_app(EEGSettings(data_dir=tmp_path))) as client:
        assert client.get("/live").json()["unfinished_recordings"] == ["crashed"]
        assert client.delete("/live/recording").status_code == 409
        assert client.delete("/live/recording?name=unknown").status_code == 404
        response = client.delete("/live/recording?name=crashed")
        assert response.status_code == 200, response.text
        meta = response.json()
        assert meta["duration_s"] == 6.0
        assert meta["n_actions"] == len(labelled)
        assert meta["synthetic"] is True
        assert client.get("/live").json()["unfinished_recordings"] == []
    assert not folder.exists()


def test_an_interrupted_recording_continues_under_its_name_and_keeps_the_gap(client):
    channels = EEG
    markers = _markers()[:6]
    source = VirtualEEGSource(quality=0.5, seed=9, sfreq=SFREQ, channels=channels)
    for part, (start, stop) in enumerate(((0.0, 4.0), (6.0, 10.0))):
        source.generate_until(start)  # the outage: generated, never sent
        with client.websocket_connect("/live/ingest") as ws:
            ingest = VirtualIngestClient(source, AsgiConnection(ws))
            response = client.post("/live/recording", json={"name": "session-7"})
            assert response.status_code == 201
            assert response.json()["resumed"] is (part == 1)
            for marker in markers:
                if start <= marker.timestamp < stop - 1.0:
                    ingest.push_epoch(marker)
                    client.post("/live/markers", json=marker.model_dump(mode="json"))
            ingest.push_until(stop)
            if part == 0:  # the EEG service "crashes": the recorder is closed, not finalised
                service = client.app.state.service
                service._recorder.close()
                service._recorder = None
    response = client.delete("/live/recording?name=session-7")
    assert response.status_code == 200, response.text
    meta = response.json()
    assert meta["duration_s"] == 8.0
    assert meta["notes"] == ["the stream had 1 gap(s); samples are concatenated"]
    sent = [m for m in markers if m.timestamp < 3.0 or 6.0 <= m.timestamp < 9.0]
    assert meta["n_actions"] == sum(m.correct is not None for m in sent)


def test_recording_names_are_checked(client):
    response = client.post("/live/recording", json={"name": "../etc"})
    assert response.status_code == 422
    assert response.json()["detail"][0]["field"] == "name"
    assert client.delete("/live/recording?name=a%2Fb").status_code == 422


def _record(client, name: str, seconds: float = 6.0) -> None:
    """Record ``seconds`` of the virtual subject with three labelled markers under ``name``."""
    markers = _markers()[:3]
    source = VirtualEEGSource(quality=0.5, seed=9, sfreq=SFREQ, channels=EEG)
    with client.websocket_connect("/live/ingest") as ws:
        ingest = VirtualIngestClient(source, AsgiConnection(ws))
        response = client.post("/live/recording", json={"name": name})
        assert response.status_code == 201, response.text
        assert response.json()["resumed"] is False
        for marker in markers:
            ingest.push_epoch(marker)
            client.post("/live/markers", json=marker.model_dump(mode="json"))
        ingest.push_until(seconds)


class _Killed(Exception):  # noqa: N818 (what it stands for)
    """Stands for the EEG service's process being killed at that point."""


@pytest.mark.parametrize("removed_before_kill", [(), (INDEX_FILE, SAMPLES_FILE)])
def test_a_crash_between_storing_and_removing_the_folder_leaves_no_folder(
    tmp_path, monkeypatch, removed_before_kill
):
    """Killed after the BDF is stored, before (or while) its folder is removed: the stored
    recording is intact; asking again answers it, a restart removes the folder, and the
    name starts a new recording instead of continuing the stored one."""

    def killed(folder) -> None:
        for file in removed_before_kill:
            (folder / file).unlink()
        raise _Killed

    settings = EEGSettings(data_dir=tmp_path)
    folders = tmp_path / "eeg" / "live_recordings"
    with TestClient(create_app(settings)) as client:
        _record(client, "cal-9")
        with monkeypatch.context() as patch:
            patch.setattr(EEGService, "_remove_folder", staticmethod(killed))
            with pytest.raises(_Killed):
                client.delete("/live/recording")
        assert (folders / "cal-9" / STORED_FILE).is_file()  # the stale folder
        (stored,) = client.get("/recordings").json()
        assert client.get("/live").json()["unfinished_recordings"] == []
    assert [p.name for p in folders.iterdir()] == ["cal-9"]

    # Restart: the folder is removed; the recording stays whole and readable.
    with TestClient(create_app(settings)) as client:
        assert not folders.exists() or list(folders.iterdir()) == []
        assert client.get("/recordings").json() == [stored]
        path = client.app.state.service.recordings.file(stored["id"])
        assert file_sha256(path) == stored["sha256"] == stored["id"]
        raw = read_recording(path, ch_names=EEG)
        assert len(action_events(raw)) == stored["n_actions"] == 3
        assert stored["duration_s"] == 6.0
        assert client.delete("/live/recording?name=cal-9").status_code == 404


def test_storing_again_after_the_crash_answers_the_stored_recording(tmp_path, monkeypatch):
    def killed(folder) -> None:
        raise _Killed

    with TestClient(create_app(EEGSettings(data_dir=tmp_path))) as client:
        _record(client, "cal-3")
        with monkeypatch.context() as patch:
            patch.setattr(EEGService, "_remove_folder", staticmethod(killed))
            with pytest.raises(_Killed):
                client.delete("/live/recording")
        (stored,) = client.get("/recordings").json()
        again = client.delete("/live/recording?name=cal-3")  # a resumed finish asks again
        assert again.status_code == 200, again.text
        assert again.json() == stored
        assert not (tmp_path / "eeg" / "live_recordings" / "cal-3").exists()
        assert client.get("/recordings").json() == [stored]

        # A stored name is not continued: recording under it again starts anew.
        with monkeypatch.context() as patch:
            patch.setattr(EEGService, "_remove_folder", staticmethod(killed))
            _record(client, "cal-4")
            with pytest.raises(_Killed):
                client.delete("/live/recording")
        _record(client, "cal-4", seconds=7.0)  # asserts resumed is False
        meta = client.delete("/live/recording").json()
        assert meta["duration_s"] == 7.0
        assert len(client.get("/recordings").json()) == 3
