"""Recording uploads: streamed with a size limit, checksummed, validated by the EEG service."""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.core.db.models import Artifact, Recording
from tests.api.conftest import Api, calibration_session, make_settings, start_api
from tests.helpers import serve_in_thread


@pytest.fixture(scope="module")
def synthetic_bdf(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A small synthetic recording (virtual subject, 256 Hz, 12 actions) as BDF bytes."""
    from services.eeg.recordings.io import write_bdf
    from services.eeg.virtual.subject import SyntheticRecording

    path = tmp_path_factory.mktemp("bdf") / "s01.bdf"
    recording = SyntheticRecording([True, False] * 6, quality=0.8, seed=1, sfreq=256.0)
    write_bdf(recording, path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def eeg_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The real EEG service on a free loopback port (a uvicorn server in a thread)."""
    from services.eeg.service.app import create_app as create_eeg_app
    from services.eeg.service.settings import EEGSettings

    settings = EEGSettings(data_dir=tmp_path_factory.mktemp("eeg"), max_upload_bytes=4 * 2**20)
    with serve_in_thread(create_eeg_app(settings)) as url:
        yield url


@pytest.fixture
def api_with_eeg(tmp_path: Path, eeg_url: str) -> Iterator[Api]:
    settings = make_settings(
        tmp_path / "data",
        f"sqlite:///{tmp_path / 'bgrl.db'}",
        eeg_url=eeg_url,
        max_upload_bytes=2 * 2**20,
    )
    yield from start_api(settings)


def test_multipart_upload_is_validated_by_the_eeg_service(
    api_with_eeg: Api, synthetic_bdf: bytes
) -> None:
    api = api_with_eeg
    session_id = calibration_session(api)
    response = api.client.post(
        f"/api/v1/sessions/{session_id}/recordings",
        files={"file": ("s01.bdf", synthetic_bdf, "application/octet-stream")},
        headers=api.as_("staff"),
    )
    assert response.status_code == 201, response.text
    recording = response.json()
    digest = hashlib.sha256(synthetic_bdf).hexdigest()
    assert (recording["sha256"], recording["size_bytes"]) == (digest, len(synthetic_bdf))
    assert (recording["validation_status"], recording["validation_reason"]) == ("valid", None)
    assert recording["synthetic"] is True
    assert (recording["sfreq"], recording["n_channels"]) == (256.0, 65)
    assert recording["duration_s"] == pytest.approx(2.0 + 12 * 1.5 + 2.0, abs=0.01)
    download = api.client.get(
        f"/api/v1/recordings/{recording['id']}/file", headers=api.as_("viewer")
    )
    assert download.content == synthetic_bdf
    assert download.headers["x-checksum-sha256"] == digest
    listed = api.client.get(
        f"/api/v1/recordings?session_id={session_id}", headers=api.as_("viewer")
    )
    assert [r["id"] for r in listed.json()["items"]] == [recording["id"]]


def test_raw_upload_of_a_bad_file_is_stored_as_invalid_with_the_reason(api_with_eeg: Api) -> None:
    api = api_with_eeg
    session_id = calibration_session(api)
    garbage = b"0       " + b"not really an EDF header" * 20
    response = api.client.post(
        f"/api/v1/sessions/{session_id}/recordings?filename=broken.edf",
        content=garbage,
        headers={**api.as_("staff"), "content-type": "application/octet-stream"},
    )
    assert response.status_code == 201, response.text
    recording = response.json()
    assert recording["sha256"] == hashlib.sha256(garbage).hexdigest()
    assert recording["validation_status"] == "invalid"
    assert recording["validation_reason"]
    assert recording["synthetic"] is None


def test_upload_limits_and_bad_requests(api: Api) -> None:
    session_id = calibration_session(api)
    url = f"/api/v1/sessions/{session_id}/recordings"
    staff = {**api.as_("staff"), "content-type": "application/octet-stream"}
    too_big = api.client.post(
        f"{url}?filename=big.bdf", content=b"x" * (64 * 1024 + 1), headers=staff
    )
    assert too_big.status_code == 413
    assert too_big.json() == {
        "detail": "file larger than the limit of 65536 bytes",
        "field": "file",
    }
    envelope = api.client.post(
        f"{url}?filename=big.bdf", content=b"x" * (128 * 1024 + 1), headers=staff
    )
    assert envelope.status_code == 413
    assert envelope.json()["field"] == "body"

    def chunks() -> Iterator[bytes]:  # no Content-Length: the limit applies while streaming
        for _ in range(80):
            yield b"y" * 1024

    streamed = api.client.post(f"{url}?filename=big.bdf", content=chunks(), headers=staff)
    assert streamed.status_code == 413
    multipart = api.client.post(
        url, files={"file": ("big.bdf", b"z" * (80 * 1024))}, headers=api.as_("staff")
    )
    assert multipart.status_code == 413
    assert multipart.json()["field"] == "file"
    wrong_type = api.client.post(f"{url}?filename=notes.txt", content=b"hello", headers=staff)
    assert wrong_type.status_code == 415
    assert wrong_type.json() == {
        "detail": "'notes.txt' is not a recording; send one of .bdf, .edf, .fif, .set, .xdf, .zip",
        "field": "filename",
    }
    no_name = api.client.post(url, content=b"hello", headers=staff)
    assert no_name.status_code == 422
    assert no_name.json()["field"] == "filename"
    empty = api.client.post(f"{url}?filename=empty.bdf", content=b"", headers=staff)
    assert empty.status_code == 422
    assert empty.json() == {"detail": "the recording is empty", "field": "file"}
    no_part = api.client.post(url, files={"other": ("a.bdf", b"abc")}, headers=api.as_("staff"))
    assert no_part.status_code == 422
    assert no_part.json()["field"] == "file"
    unknown = api.client.post(
        "/api/v1/sessions/999/recordings?filename=a.bdf", content=b"abc", headers=staff
    )
    assert unknown.status_code == 404
    assert unknown.json() == {"detail": "no session with id 999", "field": "session_id"}
    # nothing was kept of the refused uploads
    store_root = api.settings.resolved_artifact_dir
    assert [p for p in store_root.rglob("*") if p.is_file()] == []
    with api.client.app.state.sessions() as db:
        assert db.query(Recording).count() == 0
        assert db.query(Artifact).count() == 0


def test_without_an_eeg_service_the_recording_stays_pending(api: Api) -> None:
    session_id = calibration_session(api)
    response = api.client.post(
        f"/api/v1/sessions/{session_id}/recordings?filename=s.bdf",
        content=b"abc",
        headers={**api.as_("staff"), "content-type": "application/octet-stream"},
    )
    recording = response.json()
    assert recording["validation_status"] == "pending"
    assert recording["validation_reason"] == "no EEG service configured (BGRL_EEG_URL)"
    calibration = api.client.post(
        "/api/v1/jobs",
        json={"kind": "eeg_calibration", "config": {"recording_id": recording["id"]}},
        headers=api.as_("staff"),
    )
    assert calibration.status_code == 422
    assert calibration.json() == {
        "detail": f"recording {recording['id']} is pending, not valid",
        "field": "config.recording_id",
    }


def test_subject_with_recordings_needs_an_admin_purge(api: Api) -> None:
    session_id = calibration_session(api)
    subject_id = api.client.get(f"/api/v1/sessions/{session_id}", headers=api.as_("staff")).json()[
        "subject_id"
    ]
    uploaded = api.client.post(
        f"/api/v1/sessions/{session_id}/recordings?filename=s.bdf",
        content=b"abc",
        headers={**api.as_("staff"), "content-type": "application/octet-stream"},
    ).json()
    file_path = api.settings.resolved_artifact_dir / "recording"
    assert len([p for p in file_path.rglob("*") if p.is_file()]) == 1
    url = f"/api/v1/subjects/{subject_id}"
    refused = api.client.delete(url, headers=api.as_("staff"))
    assert refused.status_code == 409
    assert refused.json()["field"] == "purge"
    staff_purge = api.client.delete(f"{url}?purge=true", headers=api.as_("staff"))
    assert staff_purge.status_code == 403
    purged = api.client.delete(f"{url}?purge=true", headers=api.as_("admin"))
    assert purged.status_code == 204
    assert [p for p in file_path.rglob("*") if p.is_file()] == []
    gone = api.client.get(f"/api/v1/recordings/{uploaded['id']}", headers=api.as_("admin"))
    assert gone.status_code == 404
    entry = api.client.get("/api/v1/audit?action=subject.purge", headers=api.as_("admin")).json()
    assert entry["items"][0]["detail"] == {
        "code": "S01",
        "recordings": 1,
        "classifiers": 0,
        "live_runs": 0,
        "feedback_labels": 0,
        "files": 1,
    }
    assert entry["items"][0]["actor_email"] == "admin@lab.test"
