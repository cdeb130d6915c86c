"""The EEG service: uploads, calibration jobs, classifiers, live decoding, bad inputs."""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.eeg.decoding.calibration import CalibrationCancelled
from services.eeg.recordings.io import action_events, write_bdf
from services.eeg.service import jobs as jobs_module
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.virtual.subject import simulate_recording

SFREQ = 512.0
N_ACTIONS = 40
LIMIT = 8 * 1024 * 1024


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, object]:
    labels = (np.random.default_rng(1).random(N_ACTIONS) < 0.4).tolist()
    raw = simulate_recording(labels, quality=1.0, seed=1, sfreq=SFREQ)
    path = write_bdf(raw, tmp_path_factory.mktemp("rec") / "subject.bdf")
    return path, raw


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, max_upload_bytes=LIMIT, epoch_wait_s=0.5)
    with TestClient(create_app(settings)) as c:
        yield c


def _upload(client: TestClient, path: Path, filename: str | None = None):
    return client.post(
        "/recordings", params={"filename": filename or path.name}, content=path.read_bytes()
    )


def _upload_form(client: TestClient, data: bytes, filename: str, field: str = "file"):
    return client.post("/recordings", files={field: (filename, data)})


def _stored(client: TestClient) -> list[str]:
    """Every file the service keeps for recordings, incoming uploads included."""
    root = client.app.state.service.settings.eeg_dir
    found = [*root.glob("recordings/*"), *root.glob("incoming/**/*"), *root.glob(".tmp/*")]
    return sorted(p.name for p in found if p.is_file())


def test_raw_and_multipart_uploads_list_and_duplicate(client, recording):
    path, _ = recording
    response = _upload(client, path)
    assert response.status_code == 201, response.text
    meta = response.json()
    assert meta["synthetic"] is True
    assert meta["format"] == "bdf"
    assert meta["n_actions"] == N_ACTIONS
    assert meta["n_channels"] == 65
    assert meta["size_bytes"] == path.stat().st_size
    assert meta["sha256"] == meta["id"] and len(meta["id"]) == 64
    again = _upload_form(client, path.read_bytes(), "again.bdf")
    assert again.status_code == 200 and again.json()["id"] == meta["id"]
    assert [r["id"] for r in client.get("/recordings").json()] == [meta["id"]]
    assert client.get(f"/recordings/{meta['id']}").json()["filename"] == "subject.bdf"
    missing = client.get("/recordings/deadbeef")
    assert missing.status_code == 404
    assert missing.json() == {"detail": "no recording 'deadbeef'", "field": "recording_id"}
    assert _stored(client) == sorted([f"{meta['id']}.bdf", f"{meta['id']}.json"])


def test_multipart_upload_of_a_bdf_named_edf_is_stored_as_bdf(client, recording):
    path, _ = recording
    response = _upload_form(client, path.read_bytes(), "subject.edf")
    assert response.status_code == 201, response.text
    meta = response.json()
    assert (meta["format"], meta["filename"], meta["n_actions"]) == ("bdf", "subject.edf", 40)
    assert meta["notes"] == ["subject.edf: the file's header says BDF, not EDF; it is read as BDF"]
    assert _stored(client) == sorted([f"{meta['id']}.bdf", f"{meta['id']}.json"])


def test_bad_uploads_are_refused_and_leave_nothing(client, recording, tmp_path):
    path, raw = recording
    junk = client.post("/recordings", params={"filename": "junk.bdf"}, content=b"\x00" * 4096)
    assert junk.status_code == 415
    assert junk.json() == {
        "detail": "junk.bdf: not a readable BDF, EDF, FIF, BrainVision, EEGLAB or XDF file "
        "(its first bytes match none of them)",
        "field": "file",
    }
    truncated = path.read_bytes()[: path.stat().st_size // 2]
    cut = client.post("/recordings", params={"filename": "cut.bdf"}, content=truncated)
    assert cut.status_code == 422 and cut.json()["detail"].startswith("cut.bdf: truncated")
    assert str(tmp_path) not in cut.json()["detail"]
    missing = tmp_path / "missing_raw.fif"
    raw.copy().crop(0, 20).drop_channels(["Cz"]).save(missing, verbose="error")
    response = _upload_form(client, missing.read_bytes(), "missing_raw.fif")
    assert response.status_code == 422
    assert response.json()["detail"].startswith(
        "missing_raw.fif: missing the fronto-central sites the ErrP is decoded from: Cz ("
    )
    wrong_field = _upload_form(client, path.read_bytes(), "subject.bdf", field="recording")
    assert wrong_field.status_code == 422
    assert wrong_field.json()["field"] == "recording"
    for big in (
        client.post("/recordings", params={"filename": "big.bdf"}, content=b"\x00" * (LIMIT + 1)),
        _upload_form(client, b"\x00" * LIMIT, "big.bdf"),
    ):
        assert big.status_code == 413
        assert big.headers["content-type"] == "application/json"
        assert f"at most {LIMIT} bytes" in big.json()["detail"]
    empty = client.post("/recordings", params={"filename": "e.bdf"}, content=b"")
    assert empty.status_code == 422 and empty.json()["field"] == "file"
    assert _stored(client) == []


def test_openapi_describes_both_upload_bodies(client):
    body = client.get("/openapi.json").json()["paths"]["/recordings"]["post"]["requestBody"]
    content = body["content"]
    assert set(content) == {"multipart/form-data", "application/octet-stream"}
    assert content["multipart/form-data"]["schema"]["properties"]["file"]["format"] == "binary"


def test_aborted_upload_logs_one_warning_and_stores_nothing(client, recording, caplog):
    path, _ = recording
    data = path.read_bytes()
    sent: list[dict] = []

    async def aborted_upload() -> None:
        messages = [
            {"type": "http.request", "body": data[:65536], "more_body": True},
            {"type": "http.disconnect"},
        ]

        async def receive() -> dict:
            return messages.pop(0) if messages else {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)

        scope = {
            "type": "http",
            "asgi": {"version": "3.0"},
            "http_version": "1.1",
            "method": "POST",
            "scheme": "http",
            "path": "/recordings",
            "raw_path": b"/recordings",
            "query_string": b"filename=subject.bdf",
            "root_path": "",
            "headers": [(b"host", b"testserver"), (b"content-length", str(len(data)).encode())],
            "client": ("127.0.0.1", 5000),
            "server": ("testserver", 80),
            "state": {},
        }
        await client.app(scope, receive, send)

    with caplog.at_level(logging.INFO):
        client.portal.call(aborted_upload)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert [r.getMessage() for r in warnings] == [
        f"upload aborted by the client ({len(data)} bytes announced); nothing was stored"
    ]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert sent[0]["status"] == 400
    assert _stored(client) == []


def _wait_job(client: TestClient, job_id: str, timeout_s: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not finish: {job}")


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('{"recording_id": "%s", "seed": NaN}', "seed"),
        ('{"recording_id": "%s", "seed": Infinity}', "seed"),
        ('{"recording_id": "%s", "seed": 1e400}', "seed"),
        ('{"recording_id": "%s", "max_epoch": 3}', "max_epoch"),
        ('{"recording_id": "%s", "max_passes": 100000}', "max_passes"),
    ],
)
def test_bad_job_bodies_are_a_422_naming_the_field(client, recording, text, field):
    recording_id = _upload(client, recording[0]).json()["id"]
    response = client.post(
        "/jobs", content=text % recording_id, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422, response.text
    body = response.json()
    named = body.get("field") or body["detail"][0]["field"]
    assert named == field
    assert client.get("/jobs").json() == []


def test_calibration_job_classifier_and_live_decoding(client, recording):
    path, raw = recording
    recording_id = _upload(client, path).json()["id"]
    unknown = client.post("/jobs", json={"recording_id": "ab" * 8})
    assert unknown.status_code == 404 and unknown.json()["field"] == "recording_id"

    started = client.post("/jobs", json={"recording_id": recording_id, "max_passes": 2})
    assert started.status_code == 202, started.text
    assert started.json()["status"] == "queued"
    job = _wait_job(client, started.json()["id"])
    assert job["status"] == "succeeded", job["error"]
    assert (job["max_passes"], job["error"], job["traceback"]) == (2, None, None)
    assert job["metrics"]["n_epochs"] == N_ACTIONS
    assert client.post(f"/jobs/{job['id']}/cancel").status_code == 409
    classifier_id = job["classifier_id"]
    (listed,) = client.get("/classifiers").json()
    assert listed["id"] == classifier_id and listed["synthetic"] is True
    assert listed["recording_id"] == recording_id
    assert {"test_accuracy", "balanced_accuracy", "roc_auc"} <= set(listed["metrics"])
    n_ch, n_times = listed["epoch_shape"]
    assert (n_ch, n_times) == (64, 103)

    epoch = np.zeros((n_ch, n_times)).tolist()
    url = f"/classifiers/{classifier_id}/classify"
    body = {"epoch": epoch, "ch_names": listed["ch_names"], "sfreq": 128.0}
    response = client.post(url, json=body)
    assert response.status_code == 200
    p_error = response.json()["p_error"]
    assert response.json()["feedback"] == ("error" if p_error >= 0.5 else "correct")
    assert isinstance(response.json()["log_likelihood_ratio"], float)  # calibrated posterior
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
            assert ws.receive_json() == {"ok": True, "n_samples": min(i + 256, stop)}
        ws.send_json({"first_timestamp": "soon", "samples": [[0.0]]})
        error = ws.receive_json()
        assert error["ok"] is False and error["error"].startswith("first_timestamp:")
        ws.send_text("not json")
        assert ws.receive_json() == {"ok": False, "error": "not JSON: 'not json'"}
        status = client.get("/live").json()
        assert status["connected"] and status["source"] == "websocket"
        assert (status["issues"], status["error"], status["n_samples"]) == ([], None, stop)

        ok = client.post("/live/markers", json={**marker, "step": 4, "timestamp": t0 + onsets[4]})
        assert ok.status_code == 200
        assert ok.json()["status"] == "ok" and ok.json()["step"] == 4
        assert feedback_ws.receive_json() == ok.json()
        later = client.post("/live/markers", json={**marker, "timestamp": t0 + onsets[9]})
        assert later.json()["status"] == "rejected"
        assert later.json()["reason"] == "no complete window within 0.5 s"
    assert client.get("/live").json()["connected"] is False
    assert client.delete("/live").json()["connected"] is False


def _fake_calibrate(started: threading.Event, *, fail: bool = False):
    def calibrate(raw, *, seed, out_dir, config, report, should_stop):
        started.set()
        if fail:
            raise RuntimeError("boom\nsecond line")
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if should_stop():
                raise CalibrationCancelled("cancelled between passes")
            time.sleep(0.01)
        raise AssertionError("the job was not cancelled")

    return calibrate


def test_jobs_can_be_cancelled_queued_or_running(client, recording, monkeypatch):
    started = threading.Event()
    monkeypatch.setattr(jobs_module, "calibrate", _fake_calibrate(started))
    recording_id = _upload(client, recording[0]).json()["id"]
    running = client.post("/jobs", json={"recording_id": recording_id}).json()
    queued = client.post("/jobs", json={"recording_id": recording_id}).json()
    cancelled = client.post(f"/jobs/{queued['id']}/cancel").json()
    assert (cancelled["status"], cancelled["cancel_requested"]) == ("cancelled", True)
    assert started.wait(30)
    requested = client.post(f"/jobs/{running['id']}/cancel").json()
    assert (requested["status"], requested["cancel_requested"]) == ("running", True)
    t0 = time.monotonic()
    done = _wait_job(client, running["id"], timeout_s=10)
    assert done["status"] == "cancelled" and time.monotonic() - t0 < 3
    assert client.get(f"/jobs/{queued['id']}").json()["status"] == "cancelled"
    again = client.post(f"/jobs/{queued['id']}/cancel")
    assert again.status_code == 409
    assert again.json() == {
        "detail": f"job '{queued['id']}' is already cancelled",
        "field": "job_id",
    }
    assert client.get("/classifiers").json() == []
    assert not list(client.app.state.service.classifiers.folder.iterdir())


def test_failed_job_keeps_its_error_and_traceback(client, recording, monkeypatch, caplog):
    monkeypatch.setattr(jobs_module, "calibrate", _fake_calibrate(threading.Event(), fail=True))
    recording_id = _upload(client, recording[0]).json()["id"]
    job_id = client.post("/jobs", json={"recording_id": recording_id}).json()["id"]
    job = _wait_job(client, job_id, timeout_s=30)
    assert (job["status"], job["error"]) == ("failed", "RuntimeError: boom")
    assert job["traceback"].startswith("Traceback (most recent call last):")
    assert job["traceback"].rstrip().endswith("RuntimeError: boom\nsecond line")
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.ERROR] == [
        f"job {job_id} failed"
    ]


def test_jobs_cut_off_by_a_restart_are_marked_failed(tmp_path):
    settings = EEGSettings(data_dir=tmp_path)
    running = {
        "id": "abcdef0123456789",
        "recording_id": "0123456789abcdef",
        "seed": 0,
        "max_passes": 5,
        "status": "running",
        "created_at": "2026-01-01T00:00:00+00:00",
    }
    older = {  # a record written before the state -> status rename
        "id": "0000000000000001",
        "recording_id": "0123456789abcdef",
        "seed": 0,
        "max_epochs": 7,
        "state": "queued",
        "created_at": "2025-12-01T00:00:00+00:00",
    }
    jobs_dir = settings.eeg_dir / "jobs"
    jobs_dir.mkdir(parents=True)
    for job in (running, older):
        (jobs_dir / f"{job['id']}.json").write_text(json.dumps(job))
    staging = settings.eeg_dir / "classifiers" / f".{running['id']}.part"
    staging.mkdir(parents=True)
    with TestClient(create_app(settings)) as client:
        restored = client.get(f"/jobs/{running['id']}").json()
        migrated = client.get(f"/jobs/{older['id']}").json()
    assert restored["status"] == "failed"
    assert restored["error"] == (
        "interrupted: the EEG service stopped before the job finished; start a new job"
    )
    assert (migrated["status"], migrated["max_passes"]) == ("failed", 7)
    assert not staging.exists()


def test_service_token_guards_every_route_but_health(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, service_token="s" * 16)
    with TestClient(create_app(settings)) as client:
        assert client.get("/health").json() == {"status": "ok", "service": "eeg"}
        refused = client.get("/recordings")
        assert refused.status_code == 401 and refused.json()["field"] == "x-service-token"
        assert client.get("/recordings", headers={"x-service-token": "s" * 16}).json() == []
