"""The EEG service: uploads, calibration jobs, classifiers, live decoding, bad inputs."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from services.eeg.app import create_app
from services.eeg.io import action_events, write_bdf
from services.eeg.settings import EEGSettings
from services.eeg.virtual_subject import simulate_recording

SFREQ = 512.0
N_ACTIONS = 40


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, object]:
    labels = (np.random.default_rng(1).random(N_ACTIONS) < 0.4).tolist()
    raw = simulate_recording(labels, quality=1.0, seed=1, sfreq=SFREQ)
    path = write_bdf(raw, tmp_path_factory.mktemp("rec") / "subject.bdf")
    return path, raw


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, max_upload_bytes=8 * 1024 * 1024, epoch_wait_s=0.5)
    with TestClient(create_app(settings)) as c:
        yield c


def _upload(client: TestClient, path: Path, filename: str | None = None):
    return client.post(
        "/recordings", params={"filename": filename or path.name}, content=path.read_bytes()
    )


def _stored(client: TestClient) -> list[str]:
    root = client.app.state.service.recordings_dir
    return sorted(p.name for p in root.iterdir())


def test_upload_list_and_duplicate(client, recording):
    path, _ = recording
    response = _upload(client, path)
    assert response.status_code == 201, response.text
    meta = response.json()
    assert meta["synthetic"] is True
    assert meta["n_actions"] == N_ACTIONS
    assert meta["n_channels"] == 65
    assert meta["sha256"] == meta["id"] and len(meta["id"]) == 64
    assert _upload(client, path).status_code == 200
    assert [r["id"] for r in client.get("/recordings").json()] == [meta["id"]]
    assert client.get(f"/recordings/{meta['id']}").json()["filename"] == "subject.bdf"
    assert client.get("/recordings/deadbeef").status_code == 404
    assert _stored(client) == sorted([f"{meta['id']}.bdf", f"{meta['id']}.json"])


def test_bad_uploads_are_rejected_and_leave_nothing(client, recording, tmp_path):
    path, raw = recording
    assert _upload(client, path, "subject.txt").status_code == 415
    junk = tmp_path / "junk.bdf"
    junk.write_bytes(b"\x00" * 4096)
    response = _upload(client, junk)
    assert response.status_code == 422
    assert "not a readable BDF" in response.json()["detail"]
    missing = tmp_path / "missing_raw.fif"
    raw.copy().crop(0, 20).drop_channels(["Cz"]).save(missing, verbose="error")
    response = _upload(client, missing)
    assert response.status_code == 422 and "(Cz)" in response.json()["detail"]
    big = tmp_path / "big.bdf"
    big.write_bytes(b"\x00" * (8 * 1024 * 1024 + 1))
    assert _upload(client, big).status_code == 413
    empty = client.post("/recordings", params={"filename": "e.bdf"}, content=b"")
    assert empty.status_code == 422
    assert _stored(client) == []


def _train(client: TestClient, recording_id: str) -> dict:
    response = client.post("/jobs", json={"recording_id": recording_id, "max_epochs": 2})
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in ("done", "failed"):
            return job
        time.sleep(0.2)
    raise AssertionError("calibration job did not finish")


def test_calibration_job_classifier_and_live_decoding(client, recording):
    path, raw = recording
    recording_id = _upload(client, path).json()["id"]
    assert client.post("/jobs", json={"recording_id": "ab" * 8}).status_code == 404
    too_long = client.post("/jobs", json={"recording_id": recording_id, "max_epochs": 10**6})
    assert too_long.status_code == 422

    job = _train(client, recording_id)
    assert job["state"] == "done", job["error"]
    classifier_id = job["classifier_id"]
    (listed,) = client.get("/classifiers").json()
    assert listed["id"] == classifier_id and listed["synthetic"] is True
    assert {"test_accuracy", "balanced_accuracy", "roc_auc"} <= set(listed["metrics"])
    n_ch, n_times = listed["epoch_shape"]

    epoch = np.zeros((n_ch, n_times)).tolist()
    url = f"/classifiers/{classifier_id}/classify"
    body = {"epoch": epoch, "ch_names": listed["ch_names"], "sfreq": 128.0}
    response = client.post(url, json=body)
    assert response.status_code == 200 and 0.0 <= response.json()["p_error"] <= 1.0
    bad_shape = client.post(url, json={**body, "epoch": epoch[:-1]})
    assert bad_shape.status_code == 422 and "channels x times" in bad_shape.json()["detail"]
    bad_rate = client.post(url, json={**body, "sfreq": 256.0})
    assert bad_rate.status_code == 422 and "128 Hz" in bad_rate.json()["detail"]
    bad_names = client.post(url, json={**body, "ch_names": listed["ch_names"][::-1]})
    assert bad_names.status_code == 422 and "order" in bad_names.json()["detail"]
    assert client.post("/classifiers/nope/classify", json=body).status_code == 404

    # Live: stream the recording over the websocket ingest, then classify markers.
    marker = {"session_id": "s", "step": 0, "episode": 0, "action": 0, "timestamp": 0.0}
    assert client.post("/live/markers", json=marker).status_code == 409
    data = raw.get_data().T
    onsets = action_events(raw)[:, 0] / SFREQ
    t0 = 5000.0
    ingest_url = f"/live/ingest?classifier_id={classifier_id}"
    with (
        client.websocket_connect(ingest_url) as ws,
        client.websocket_connect("/live/feedback") as feedback_ws,
    ):
        ws.send_json({"ch_names": raw.ch_names, "sfreq": SFREQ})
        assert ws.receive_json() == {"ok": True, "n_samples": 0}
        stop = int((onsets[5] + 2.0) * SFREQ)  # up to 2 s after the 6th action
        for i in range(0, stop, 256):
            ws.send_json({"first_timestamp": t0 + i / SFREQ, "samples": data[i : i + 256].tolist()})
            assert ws.receive_json()["ok"] is True
        ws.send_json({"first_timestamp": "soon", "samples": [[0.0]]})
        assert ws.receive_json()["ok"] is False
        status = client.get("/live").json()
        assert status["connected"] and status["source"] == "websocket" and status["issues"] == []

        ok = client.post("/live/markers", json={**marker, "step": 4, "timestamp": t0 + onsets[4]})
        assert ok.status_code == 200
        assert ok.json()["status"] == "ok" and ok.json()["feedback"] in ("correct", "error")
        assert feedback_ws.receive_json()["step"] == 4
        later = client.post("/live/markers", json={**marker, "timestamp": t0 + onsets[9]})
        assert later.json()["status"] == "rejected"
        assert "no complete window" in later.json()["reason"]
    assert client.get("/live").json()["connected"] is False
    assert client.delete("/live").json()["connected"] is False


def test_websockets_refuse_foreign_origin_and_bad_header(client, recording):
    with (
        pytest.raises(WebSocketDisconnect),
        client.websocket_connect("/live/feedback", headers={"origin": "http://evil.example"}) as ws,
    ):
        ws.receive_json()
    with (
        pytest.raises(WebSocketDisconnect),
        client.websocket_connect("/live/ingest?classifier_id=missing") as ws,
    ):
        ws.receive_json()


def _untrained_classifier(client: TestClient, ch_names: list[str], sfreq: float) -> str:
    """An (untrained) classifier stored as the service stores them; enough for plumbing."""
    import torch

    from services.eeg.classifier import ErrPClassifier
    from services.eeg.eegnet import EEGNet
    from services.eeg.preprocessing import PreprocessingParams

    torch.manual_seed(0)
    params = PreprocessingParams()
    model = EEGNet(len(ch_names), 2, params.n_times_epoch)
    clf = ErrPClassifier(model, params, ch_names, sfreq, 1e5, {"test_accuracy": 0.5})
    clf.save(client.app.state.service.classifiers_dir / "plumbing")
    return "plumbing"


@pytest.mark.lsl
def test_live_lsl_source_classifies_markers(client):
    lsl = pytest.importorskip("services.eeg.lsl")
    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    labels = [True, False, True, False, True]
    raw = simulate_recording(labels, quality=1.0, seed=2, sfreq=SFREQ, lead_in_s=2.5)
    eeg_names = raw.ch_names[:-1]
    classifier_id = _untrained_classifier(client, eeg_names, SFREQ)
    name = f"bgrl-app-{time.monotonic_ns()}"
    settings = client.app.state.service.settings
    settings.lsl_timeout_s = 0.5
    missing = client.post("/live", json={"classifier_id": classifier_id, "stream_name": "nope"})
    settings.lsl_timeout_s = 5.0
    assert missing.status_code == 422 and "nope" in missing.json()["detail"]
    from mne_lsl.lsl import resolve_streams

    from services.core.markers import ActionMarker
    from services.sim.lsl_markers import MarkerPublisher

    player = lsl.replay(raw, name=name, chunk_size=32)
    publisher = None
    try:
        response = client.post("/live", json={"classifier_id": classifier_id, "stream_name": name})
        assert response.status_code == 200, response.text
        assert response.json()["source"] == "lsl"
        ingest = client.app.state.service.live.ingest
        deadline = time.monotonic() + raw.times[-1] + 5.0
        triggers = []
        while len(triggers) < 2 and time.monotonic() < deadline:
            triggers += ingest.pop_triggers()
            time.sleep(0.05)
        marker = {"session_id": "s", "step": 1, "episode": 0, "action": 1}
        settings.epoch_wait_s = 2.0  # the window ends 0.8 s after the trigger
        feedback = client.post(
            "/live/markers", json={**marker, "timestamp": triggers[-1].timestamp}
        )
        assert feedback.status_code == 200
        assert feedback.json()["status"] == "ok", feedback.json()["reason"]
        assert feedback.json()["synthetic"] is False  # the plumbing classifier is not marked

        # Markers from the sim's LSL marker stream are classified as they arrive.
        publisher = MarkerPublisher("bgrl-test-markers", name=f"{name}-markers")
        if not (
            resolve_streams(timeout=2.0, name=publisher.name)
            and resolve_streams(timeout=2.0, name=name)
        ):
            pytest.skip(
                "liblsl resolves only one outlet per process with this LSL config; add "
                "'[lab] KnownPeers = {127.0.0.1}' to services/core/lsl_loopback.cfg"
            )
        body = {
            "classifier_id": classifier_id,
            "stream_name": name,
            "marker_stream": publisher.name,
        }
        response = client.post("/live", json=body)
        assert response.status_code == 200, response.text
        assert response.json()["marker_stream"] == publisher.name
        ingest = client.app.state.service.live.ingest
        while ingest.latest_timestamp is None and time.monotonic() < deadline:
            time.sleep(0.05)
        start = ingest.latest_timestamp
        with client.websocket_connect("/live/feedback") as ws:
            publisher.publish(ActionMarker(**{**marker, "step": 7, "timestamp": start + 1.2}))
            message = ws.receive_json()
        assert message["step"] == 7 and message["status"] == "ok", message["reason"]
    finally:
        if publisher is not None:
            publisher.close()
        client.delete("/live")
        player.stop()


def test_jobs_cut_off_by_a_restart_are_marked_failed(tmp_path):
    settings = EEGSettings(data_dir=tmp_path)
    with TestClient(create_app(settings)) as first:
        service = first.app.state.service
        job = {
            "id": "abcdef0123456789",
            "recording_id": "0123456789abcdef",
            "seed": 0,
            "max_epochs": 5,
            "state": "running",
            "created_at": "2026-01-01T00:00:00+00:00",
        }
        (service.jobs_dir / f"{job['id']}.json").write_text(json.dumps(job))
        staging = service.classifiers_dir / f".{job['id']}.part"
        staging.mkdir()
    with TestClient(create_app(settings)) as second:
        restored = second.get(f"/jobs/{job['id']}").json()
    assert restored["state"] == "failed"
    assert "interrupted" in restored["error"]
    assert not staging.exists()
