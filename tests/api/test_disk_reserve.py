"""A nearly full data disk: uploads, new jobs, retries and live starts are refused with 507.

The reserve (``BGRL_MIN_FREE_MB``) is set above the disk's free space instead of filling
the disk (tests/core/test_disk.py meets a real ENOSPC on a small tmpfs).
"""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from services.core.db.models import Job
from tests.api.conftest import Api, calibration_session
from tests.api.test_jobs import GUIDED, broker_messages, submit

ABOVE_FREE_MB = 10**9
"""A reserve larger than any disk here: every check refuses."""


def _files_below(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def test_api_refuses_uploads_jobs_retries_and_live_starts_below_the_reserve(api: Api) -> None:
    staff = api.as_("staff")
    session_id = calibration_session(api)
    failed = submit(api, "guided_ppo", GUIDED).json()
    broker_messages(api)
    store_root = api.client.app.state.store.root
    files_before = _files_below(store_root)

    api.settings.min_free_mb = ABOVE_FREE_MB
    url = f"/api/v1/sessions/{session_id}/recordings"
    raw = api.client.post(
        f"{url}?filename=s01.bdf",
        content=b"x" * 1000,
        headers={**staff, "content-type": "application/octet-stream"},
    )
    multipart = api.client.post(url, files={"file": ("s01.bdf", b"x" * 1000)}, headers=staff)
    job = submit(api, "guided_ppo", GUIDED)
    with api.client.app.state.sessions() as db:
        db.get(Job, failed["id"]).status = "failed"
        db.commit()
    retry = api.client.post(f"/api/v1/jobs/{failed['id']}/retry", headers=staff)
    live = api.client.post(f"/api/v1/sessions/{session_id}/start", json={}, headers=staff)
    for response in (raw, multipart, job, retry, live):
        assert response.status_code == 507, response.text
        assert "BGRL_MIN_FREE_MB" in response.json()["detail"]
    assert "the upload is refused" in raw.json()["detail"]
    assert "a new job is refused" in job.json()["detail"]
    assert _files_below(store_root) == files_before
    assert api.client.get("/api/v1/recordings", headers=staff).json()["items"] == []
    jobs = api.client.get("/api/v1/jobs", headers=staff).json()
    assert [(j["id"], j["status"]) for j in jobs["items"]] == [(failed["id"], "failed")]
    assert broker_messages(api) == []

    api.settings.min_free_mb = 1
    assert submit(api, "guided_ppo", GUIDED).status_code == 201


def test_eeg_service_refuses_uploads_and_calibration_jobs_below_the_reserve(tmp_path: Path) -> None:
    from services.eeg.service.app import create_app
    from services.eeg.service.settings import EEGSettings

    settings = EEGSettings(data_dir=tmp_path, min_free_mb=ABOVE_FREE_MB)
    with TestClient(create_app(settings)) as client:
        raw = client.post("/recordings", params={"filename": "a.bdf"}, content=b"x" * 1000)
        form = client.post("/recordings", files={"file": ("a.bdf", b"x" * 1000)})
        job = client.post("/jobs", json={"recording_id": "0" * 64})
        for response in (raw, form, job):
            assert response.status_code == 507, response.text
        assert "a new calibration job is refused" in job.json()["detail"]
        assert _files_below(settings.eeg_dir) == []
        assert client.get("/recordings").json() == []
