"""``bgrl backup`` / ``bgrl restore``: an online backup of a running platform, restored into a
fresh data folder and database, rows and files checked (SQLite, and PostgreSQL if present)."""

from __future__ import annotations

import hashlib
import json
import stat
import tarfile
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import create_engine, make_url, text
from typer.testing import CliRunner

from services.cli.main import app
from services.core.db.migrate import head_revision
from tests.api.conftest import Api, calibration_session, make_settings, start_api

runner = CliRunner()
RECORDING = b"BDF-like bytes of a recording " * 100
EEG_FILE = b"a classifier the EEG service keeps " * 10
IN_PROGRESS = ("eeg/incoming/.tmp/u.part", "eeg/classifiers/.job1.part/c.pt", "api/.x.json.1.tmp")


@pytest.fixture(params=["sqlite", "postgresql"])
def source_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """The platform's database: the SQLite file in its data folder, or a PostgreSQL schema."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'data' / 'bgrl.db'}"
    else:
        yield request.getfixturevalue("pg_url")


@pytest.fixture
def running(tmp_path: Path, source_url: str) -> Iterator[Api]:
    """A running api with a subject, a session, an uploaded recording and a job."""
    data = tmp_path / "data"
    for api in start_api(make_settings(data, source_url)):
        staff = api.as_("staff")
        session_id = calibration_session(api)
        upload = api.client.post(
            f"/api/v1/sessions/{session_id}/recordings?filename=s01.bdf",
            content=RECORDING,
            headers={**staff, "content-type": "application/octet-stream"},
        )
        assert upload.status_code == 201, upload.text
        job = api.client.post(
            "/api/v1/jobs",
            json={"kind": "guided_ppo", "config": {"task": "SSSG", "method": "rl_sparse"}},
            headers=staff,
        )
        assert job.status_code == 201, job.text
        (data / "eeg" / "classifiers").mkdir(parents=True)
        (data / "eeg" / "classifiers" / "c1.pt").write_bytes(EEG_FILE)
        for in_progress in IN_PROGRESS:  # not backed up: not complete yet
            (data / in_progress).parent.mkdir(parents=True, exist_ok=True)
            (data / in_progress).write_bytes(b"half")
        yield api


def _rows(url: str) -> dict[str, list[tuple[object, ...]]]:
    engine = create_engine(url)
    try:
        with engine.connect() as connection:
            return {
                table: [tuple(row) for row in connection.execute(text(query))]
                for table, query in {
                    "subjects": "SELECT id, code FROM subjects ORDER BY id",
                    "recordings": "SELECT id, sha256 FROM recordings ORDER BY id",
                    "jobs": "SELECT id, kind, status FROM jobs ORDER BY id",
                    "users": "SELECT email, password_hash FROM users ORDER BY id",
                }.items()
            }
    finally:
        engine.dispose()


def _files(root: Path) -> dict[str, str]:
    return {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in root.rglob("*")
        if p.is_file()
    }


@pytest.fixture
def restore_url(source_url: str, tmp_path: Path) -> Iterator[str]:
    """A fresh database to restore into: a SQLite file, or a new PostgreSQL database with
    the source's schema name (created and dropped here)."""
    if source_url.startswith("sqlite"):
        yield f"sqlite:///{tmp_path / 'restored' / 'bgrl.db'}"
        return
    source = make_url(source_url)
    name = f"bgrl_restore_{uuid.uuid4().hex[:10]}"
    admin = create_engine(source.set(query={}), isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield source.set(database=name).render_as_string(hide_password=False)
    finally:
        with admin.connect() as connection:
            connection.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
        admin.dispose()


def _env(data: Path, url: str) -> dict[str, str | None]:
    return {"BGRL_DATA_DIR": str(data), "BGRL_DATABASE_URL": url, "BGRL_ARTIFACT_DIR": None}


def test_online_backup_restores_rows_and_files_into_a_fresh_folder(
    running: Api, source_url: str, restore_url: str, tmp_path: Path
) -> None:
    data = tmp_path / "data"
    archive = tmp_path / "backups" / "lab.tar"
    before = _rows(source_url)
    assert [len(before[t]) for t in ("subjects", "recordings", "jobs")] == [1, 1, 1]
    writer = create_engine(source_url)
    with writer.connect() as open_write:  # a transaction in flight is not in the backup
        open_write.execute(text("UPDATE subjects SET code = 'S99'"))
        result = runner.invoke(app, ["backup", str(archive)], env=_env(data, source_url))
        open_write.rollback()
    writer.dispose()
    assert result.exit_code == 0, result.output
    assert stat.S_IMODE(archive.stat().st_mode) == 0o600
    assert stat.S_IMODE(archive.parent.stat().st_mode) == 0o700

    with tarfile.open(archive) as tar:
        manifest = json.loads(tar.extractfile("manifest.json").read())  # type: ignore[union-attr]
        assert {m.name for m in tar if m.name != "manifest.json"} == set(manifest["members"])
    assert manifest["database"]["schema_revision"] == head_revision()
    assert manifest["versions"]["bgrl"] and manifest["versions"]["alembic"]
    members = manifest["members"]
    recording_sha = hashlib.sha256(RECORDING).hexdigest()
    assert [m["sha256"] for n, m in members.items() if n.startswith("artifacts/recording/")] == [
        recording_sha
    ]
    assert "data/eeg/classifiers/c1.pt" in members and "data/api/jwt.key" in members
    assert (data / "broker").is_dir()  # the embedded broker holds the job's message
    skipped = (
        "data/bgrl.db",
        "data/broker/",
        "data/artifacts/",
        *(f"data/{f}" for f in IN_PROGRESS),
    )
    assert not [n for n in members if n.startswith(skipped)]

    restored = tmp_path / "restored"
    result = runner.invoke(app, ["restore", str(archive)], env=_env(restored, restore_url))
    assert result.exit_code == 0, result.output
    assert _rows(restore_url) == before  # not S99
    source_files = {
        k: v
        for k, v in _files(data).items()
        if not k.startswith(("bgrl.db", "broker/", *IN_PROGRESS))
    }
    restored_files = {k: v for k, v in _files(restored).items() if k != "bgrl.db"}
    assert restored_files == source_files
    for path in restored.rglob("*"):
        assert stat.S_IMODE(path.stat().st_mode) == (0o700 if path.is_dir() else 0o600), path

    again = runner.invoke(app, ["restore", str(archive)], env=_env(restored, restore_url))
    assert (
        again.exit_code == 1
        and "already holding data" in again.output
        and "--force" in again.output
    )
    forced = runner.invoke(
        app, ["restore", "--force", str(archive)], env=_env(restored, restore_url)
    )
    assert forced.exit_code == 0, forced.output
    assert _rows(restore_url) == before


def test_a_damaged_archive_restores_nothing(tmp_path: Path) -> None:
    data = tmp_path / "data"
    url = f"sqlite:///{data / 'bgrl.db'}"
    for _api in start_api(make_settings(data, url)):
        (data / "eeg").mkdir()
        (data / "eeg" / "r.bdf").write_bytes(RECORDING)
        archive = tmp_path / "lab.tar"
        assert runner.invoke(app, ["backup", str(archive)], env=_env(data, url)).exit_code == 0
    raw = bytearray(archive.read_bytes())
    at = raw.index(RECORDING)
    raw[at + 10] ^= 0xFF
    damaged = tmp_path / "damaged.tar"
    damaged.write_bytes(bytes(raw))
    fresh = tmp_path / "fresh"
    result = runner.invoke(
        app, ["restore", str(damaged)], env=_env(fresh, f"sqlite:///{fresh / 'bgrl.db'}")
    )
    assert result.exit_code == 1
    assert "data/eeg/r.bdf does not match its checksum" in result.output
    assert [p for p in fresh.rglob("*") if p.is_file()] == []

    inside = runner.invoke(app, ["backup", str(data / "b.tar")], env=_env(data, url))
    assert inside.exit_code == 1 and "write the backup elsewhere" in inside.output
    not_ours = tmp_path / "other.tar"
    with tarfile.open(not_ours, "w") as tar:
        tar.add(data / "eeg" / "r.bdf", arcname="r.bdf")
    refused = runner.invoke(app, ["restore", str(not_ours)], env=_env(fresh, url))
    assert refused.exit_code == 1 and "not a backup made by `bgrl backup`" in refused.output
