"""The platform api served by uvicorn on loopback (SQLite in a temp folder) for client tests."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI

from services.api.app import create_app
from services.api.settings import ApiSettings
from services.client import PlatformClient
from services.core.db.models import Artifact, Job
from tests.helpers import fast_password_hashing, serve_in_thread

ADMIN_EMAIL = "admin@lab.test"
ADMIN_PASSWORD = "admin-password-123"
STAFF_EMAIL = "staff@lab.test"
VIEWER_EMAIL = "viewer@lab.test"
PASSWORD = "a-long-password-1"
MODEL_BYTES = b"PK\x03\x04 a stand-in for a TorchScript archive " * 100


@dataclass
class LiveApi:
    """A running api: its URL, app (for direct database access) and settings."""

    url: str
    app: FastAPI
    settings: ApiSettings

    def finished_job_with_model(self, data: bytes = MODEL_BYTES) -> tuple[str, Path]:
        """A succeeded guided_ppo job whose model is ``data`` in the artifact store: the
        job's id and the stored file (what a worker leaves behind)."""
        stored = self.app.state.store.put_bytes(data, kind="model", name="policy.pt")
        with self.app.state.sessions() as db:
            job = Job(
                kind="guided_ppo",
                config={"task": "sssg", "method": "rl_sparse", "seed": 0, "total_steps": 2000},
                status="succeeded",
                progress=1.0,
            )
            db.add(job)
            db.flush()
            artifact = Artifact(
                kind="model",
                relpath=stored.relpath,
                sha256=stored.sha256,
                size_bytes=stored.size_bytes,
                job_id=job.id,
            )
            db.add(artifact)
            db.flush()
            job.model_artifact_id = artifact.id
            db.commit()
            return job.id, self.app.state.store.path(stored.relpath)


@pytest.fixture
def credentials(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """Where the CLI keeps its token in this test (no BGRL_API_URL / BGRL_API_TOKEN)."""
    path = tmp_path / "config" / "bgrl" / "credentials.json"
    monkeypatch.setenv("BGRL_CREDENTIALS_FILE", str(path))
    monkeypatch.delenv("BGRL_API_URL", raising=False)
    monkeypatch.delenv("BGRL_API_TOKEN", raising=False)
    return path


@pytest.fixture(scope="module")
def live_api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveApi]:
    """The api on 127.0.0.1 (a free port) with an admin, a staff and a viewer account."""
    patch = pytest.MonkeyPatch()
    fast_password_hashing(patch)
    root = tmp_path_factory.mktemp("live-api")
    settings = ApiSettings(
        data_dir=root / "data",
        database_url=f"sqlite:///{root / 'bgrl.db'}",
        broker_url=None,
        admin_email=ADMIN_EMAIL,
        admin_password=ADMIN_PASSWORD,
        eeg_url=None,
    )
    app = create_app(settings)
    try:
        with serve_in_thread(app) as url:
            live = LiveApi(url=url, app=app, settings=settings)
            add_accounts(live)
            yield live
    finally:
        patch.undo()


def add_accounts(live: LiveApi) -> None:
    """A staff and a viewer account besides the settings' admin."""
    with PlatformClient(live.url) as admin:
        admin.login(ADMIN_EMAIL, ADMIN_PASSWORD)
        for email, role in ((STAFF_EMAIL, "staff"), (VIEWER_EMAIL, "viewer")):
            response = httpx.post(
                f"{live.url}/api/v1/users",
                json={"email": email, "password": PASSWORD, "role": role},
                headers={"Authorization": f"Bearer {admin.token}"},
            )
            assert response.status_code == 201, response.text


@pytest.fixture
def staff(live_api: LiveApi) -> Iterator[PlatformClient]:
    """A client signed in as staff."""
    with PlatformClient(live_api.url) as client:
        client.login(STAFF_EMAIL, PASSWORD)
        yield client
