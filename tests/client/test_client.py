"""PlatformClient against the real api on loopback: auth, subjects, sessions, jobs, downloads."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest

from services.client import (
    ChecksumMismatchError,
    Job,
    PlatformClient,
    PlatformError,
    WaitTimeoutError,
)
from tests.client.conftest import MODEL_BYTES, PASSWORD, STAFF_EMAIL, VIEWER_EMAIL, LiveApi

GUIDED = {"task": "sssg", "method": "hf_sparse", "accuracy": 0.7, "seed": 3, "total_steps": 2000}


def test_login_refused_with_status_and_field(live_api: LiveApi) -> None:
    with PlatformClient(live_api.url) as client, pytest.raises(PlatformError) as caught:
        client.login(STAFF_EMAIL, "not-the-password")
    assert caught.value.status == 401
    assert caught.value.field == "password"
    assert caught.value.detail == "wrong e-mail or password, or account deactivated"
    assert client.token is None


def test_api_token_signs_in_and_a_wrong_one_is_refused(
    live_api: LiveApi, staff: PlatformClient
) -> None:
    created = staff.create_api_token("script", expires_in_days=1)
    assert created.token is not None and created.token.startswith("bgrl_")
    with PlatformClient(live_api.url) as script:
        user = script.login_with_api_token(created.token)
        assert (user.email, user.role) == (STAFF_EMAIL, "staff")
        assert script.list_jobs(limit=1).limit == 1
        staff.revoke_api_token(created.id)
        with pytest.raises(PlatformError) as caught:
            script.login_with_api_token(created.token)
    assert (caught.value.status, caught.value.field) == (401, "token")
    assert script.token is None


def test_submit_list_cancel_and_wait(staff: PlatformClient) -> None:
    job = staff.submit_job("guided_ppo", GUIDED)
    assert isinstance(job, Job)
    assert (job.kind, job.status, job.progress, job.attempts) == ("guided_ppo", "queued", 0.0, 0)
    assert job.config == {
        **GUIDED,
        "hf_treatment": "authors",
        "n_labels": 1000,
        "ppo": {},
        "preset": "paper",
    }
    queued = staff.list_jobs(status="queued", kind="guided_ppo", limit=500)
    assert job.id in [j.id for j in queued.items]
    assert queued.limit == 500

    with pytest.raises(WaitTimeoutError) as waited:
        staff.wait_job(job.id, timeout_s=0.3, poll_s=0.1)
    assert waited.value.field == "job_id"

    cancelled = staff.cancel_job(job.id)
    assert (cancelled.status, cancelled.cancel_requested) == ("cancelled", True)
    seen: list[str] = []
    final = staff.wait_job(job.id, timeout_s=5, on_progress=lambda j: seen.append(j.status))
    assert (final.status, final.finished, seen) == ("cancelled", True, ["cancelled"])
    with pytest.raises(PlatformError) as again:
        staff.cancel_job(job.id)
    assert (again.value.status, again.value.field) == (409, "job_id")
    assert again.value.detail == f"job {job.id} is already cancelled"


def test_bad_config_names_the_field(staff: PlatformClient) -> None:
    with pytest.raises(PlatformError) as caught:
        staff.submit_job("guided_ppo", {**GUIDED, "total_steps": -5})
    assert caught.value.status == 422
    assert caught.value.is_bad_input
    assert caught.value.field == "config.total_steps"
    with pytest.raises(PlatformError) as unknown:
        staff.submit_job("guided_ppo", {**GUIDED, "learning_rate": 0.1})
    assert (unknown.value.status, unknown.value.field) == (422, "config.learning_rate")


def test_stage2_method_and_reproduce_preset(staff: PlatformClient) -> None:
    job = staff.submit_job("guided_ppo", {**GUIDED, "hf_method": "categorical_info"})
    assert job.config["hf_method"] == "categorical_info"
    with pytest.raises(PlatformError) as caught:
        staff.submit_job(
            "guided_ppo", {"task": "sssg", "method": "rl_sparse", "hf_method": "paper"}
        )
    assert (caught.value.status, caught.value.field) == (422, "config.hf_method")
    sweep = staff.submit_job("reproduce", {"quick": True, "preset": "platform"})
    assert sweep.config["preset"] == "platform"
    for submitted in (job, sweep):
        staff.cancel_job(submitted.id)


def test_viewer_cannot_submit(live_api: LiveApi) -> None:
    with PlatformClient(live_api.url) as viewer:
        viewer.login(VIEWER_EMAIL, PASSWORD)
        with pytest.raises(PlatformError) as caught:
            viewer.submit_job("guided_ppo", GUIDED)
    assert (caught.value.status, caught.value.field) == (403, "role")


def test_model_download_verifies_the_checksum(
    live_api: LiveApi, staff: PlatformClient, tmp_path: Path
) -> None:
    job_id, stored = live_api.finished_job_with_model()
    saved = staff.download_model(job_id, tmp_path / "models" / "policy.pt")
    assert saved.path.read_bytes() == MODEL_BYTES
    assert saved.size_bytes == len(MODEL_BYTES)
    artifacts = staff.list_artifacts(job_id=job_id)
    assert [a.sha256 for a in artifacts.items] == [saved.sha256]
    copy = staff.download_artifact(artifacts.items[0].id, tmp_path / "copy.pt")
    assert copy.path.read_bytes() == MODEL_BYTES

    stored.write_bytes(MODEL_BYTES[:-1] + b"!")  # the stored file rots after its hash was kept
    target = tmp_path / "corrupt" / "policy.pt"
    with pytest.raises(ChecksumMismatchError) as caught:
        staff.download_model(job_id, target)
    assert "is corrupt" in caught.value.detail
    assert list(target.parent.iterdir()) == []


def test_download_of_a_job_without_model_writes_nothing(
    staff: PlatformClient, tmp_path: Path
) -> None:
    job = staff.submit_job("guided_ppo", GUIDED)
    with pytest.raises(PlatformError) as caught:
        staff.download_model(job.id, tmp_path / "policy.pt")
    assert (caught.value.status, caught.value.field) == (404, "job_id")
    assert list(tmp_path.iterdir()) == []
    staff.cancel_job(job.id)


def test_subjects_and_sessions(staff: PlatformClient) -> None:
    subject = staff.create_subject("CLIENT-S01", notes="pilot")
    assert (subject.code, subject.notes) == ("CLIENT-S01", "pilot")
    assert staff.get_subject(subject.id) == subject
    assert [s.id for s in staff.list_subjects(code="CLIENT-").items] == [subject.id]
    with pytest.raises(PlatformError) as taken:
        staff.create_subject("CLIENT-S01")
    assert (taken.value.status, taken.value.field) == (409, "code")

    start = datetime(2030, 1, 7, 9, 0, tzinfo=UTC)
    session = staff.schedule_session(subject.id, "calibration", start, duration_minutes=30)
    assert (session.status, session.ends_at) == (
        "scheduled",
        datetime(2030, 1, 7, 9, 30, tzinfo=UTC),
    )
    with pytest.raises(PlatformError) as overlap:
        staff.schedule_session(subject.id, "rl", start.replace(minute=15))
    assert (overlap.value.status, overlap.value.field) == (409, "scheduled_at")
    assert [s.id for s in staff.list_sessions(subject_id=subject.id).items] == [session.id]
    assert staff.cancel_session(session.id).status == "cancelled"

    happened = datetime(2020, 1, 1, 9, 0, tzinfo=UTC)
    with pytest.raises(PlatformError) as past:
        staff.schedule_session(subject.id, "calibration", happened)
    assert (past.value.status, past.value.field) == (422, "scheduled_at")
    assert "send allow_past: true" in str(past.value)
    confirmed = staff.schedule_session(subject.id, "calibration", happened, allow_past=True)
    assert confirmed.scheduled_at == happened


def test_unreachable_api_is_a_platform_error() -> None:
    client = PlatformClient("http://127.0.0.1:9", timeout_s=2)
    with client, pytest.raises(PlatformError) as caught:
        client.login("a@b.c", "x")
    assert caught.value.status is None
    assert str(caught.value).startswith("cannot reach http://127.0.0.1:9")
