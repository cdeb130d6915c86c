"""The finish of a calibration session is crash-safe: the worker is made to die at each step
of it (before the EEG service stores the recording, after it did, halfway through the copy
into the artifact store, after the copy, after the rows, after the follow-up job was sent,
after the run was marked completed), then the job is claimed again, as after a dead
worker, and resumes. Each time the session ends with exactly one stored recording: one
recording row, one artifact, one file in the store whose sha256 and size are the row's,
one ``eeg_calibration`` job on it, no orphan file and no second recording in the EEG
service."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import httpx
import pytest
from sqlalchemy import select

from services.core.artifacts import sha256_file
from services.core.db.live import LiveRun
from services.core.db.models import Artifact, Job, Recording
from services.worker import live_finish, live_session
from services.worker.live_eeg import EegDecoder
from services.worker.live_session import LiveRunner
from services.worker.runtime import run_job
from tests.loop.conftest import TOKEN, LoopPlatform

pytestmark = pytest.mark.slow

N_ACTIONS = 24


class WorkerDiedError(RuntimeError):
    """Raised where the test kills the worker: the attempt ends there, nothing after it runs."""


def _die_before(owner: Any, name: str, patch: pytest.MonkeyPatch) -> None:
    """The first call of ``owner.name`` dies instead of running."""
    real = getattr(owner, name)
    calls = []

    def dying(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        if len(calls) == 1:
            raise WorkerDiedError(f"before {name}")
        return real(*args, **kwargs)

    patch.setattr(owner, name, dying)


def _die_after(owner: Any, name: str, patch: pytest.MonkeyPatch) -> None:
    """The first call of ``owner.name`` runs to its end, then the worker dies."""
    real = getattr(owner, name)
    calls = []

    def dying(*args: Any, **kwargs: Any) -> Any:
        out = real(*args, **kwargs)
        calls.append(1)
        if len(calls) == 1:
            raise WorkerDiedError(f"after {name}")
        return out

    patch.setattr(owner, name, dying)


def _die_before_the_rename(patch: pytest.MonkeyPatch) -> None:
    """The copy into the artifact store is written (its temporary file synced), and the
    worker dies before renaming it into place."""
    real = os.replace
    calls = []

    def dying(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
        if str(src).endswith(".part") and str(dst).endswith("-calibration.bdf") and not calls:
            calls.append(1)
            raise WorkerDiedError("before the rename")
        real(src, dst, *args, **kwargs)

    patch.setattr(live_finish.os, "replace", dying)


CRASHES: dict[str, Callable[[pytest.MonkeyPatch], None]] = {
    "before the EEG service stores the recording": lambda p: _die_before(
        EegDecoder, "stop_recording", p
    ),
    "after the EEG service stored it": lambda p: _die_after(EegDecoder, "stop_recording", p),
    "halfway through the copy into the store": _die_before_the_rename,
    "after the copy, before the rows": lambda p: _die_before(
        live_finish.RunFinish, "recording_rows", p
    ),
    "after the rows, before the job is sent": lambda p: _die_before(live_finish, "enqueue_job", p),
    "after the job was sent": lambda p: _die_after(live_finish.RunFinish, "calibration", p),
    "after the run was marked completed": lambda p: _die_after(LiveRunner, "finish", p),
}


@pytest.mark.parametrize("crash", list(CRASHES))
def test_a_crash_in_the_finish_is_completed_by_the_resume_with_one_recording(
    loop: LoopPlatform, crash: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    session_id = loop.lab_session("calibration", subject_code="S-FINISH")
    options = {"accelerated": True, "n_actions": N_ACTIONS, "virtual_quality": 0.9, "seed": 3}
    run_id, job_id = loop.live_job(session_id, options)
    sent: list[str] = []
    real_enqueue = live_finish.enqueue_job
    monkeypatch.setattr(
        live_finish,
        "enqueue_job",
        lambda celery, job, kind: (sent.append(job), real_enqueue(celery, job, kind)),
    )
    CRASHES[crash](monkeypatch)

    assert run_job(loop.runtime, job_id, live_session.live_session) == "queued"  # died
    with loop.runtime.sessions() as db:
        died = db.get(Job, job_id)
        assert died is not None and (died.error or "").startswith("WorkerDiedError"), died.error
    assert run_job(loop.runtime, job_id, live_session.live_session) == "succeeded"

    recording, follow_up = _one_recording(loop, run_id, session_id)
    assert sent and set(sent) == {follow_up}  # sent (again, if the crash came before it)
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed" and run.resumes == 1
        assert run.result is not None and run.result["recording_sha256"] == recording.sha256
        assert run.result["recording_id"] == recording.id
        assert run.result["calibration_job_id"] == follow_up
        recorded = run.result["recorded_markers"]
    if crash.startswith("before the EEG"):  # resumed recording: at most the unflushed block
        assert N_ACTIONS - 3 <= recorded <= N_ACTIONS
    else:
        assert recorded == N_ACTIONS


def _one_recording(loop: LoopPlatform, run_id: int, session_id: int) -> tuple[Recording, str]:
    """Check that the session stored exactly one recording, whole and referenced once;
    (its row, its eeg_calibration job id)."""
    name = f"session-{session_id}-calibration.bdf"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None
        (recording,) = db.scalars(select(Recording).where(Recording.session_id == session_id))
        (artifact,) = db.scalars(select(Artifact).where(Artifact.relpath.endswith(name)))
        jobs = db.scalars(select(Job).where(Job.kind == "eeg_calibration")).all()
        follow_ups = [j for j in jobs if j.config.get("recording_id") == recording.id]
        db.expunge_all()
    assert run.recording_id == recording.id and recording.artifact_id == artifact.id
    assert [j.id for j in follow_ups] == [run.follow_up_job_id]
    assert follow_ups[0].status == "queued"
    path = loop.runtime.store.path(artifact.relpath)
    assert sha256_file(path) == recording.sha256 == artifact.sha256
    assert path.stat().st_size == recording.size_bytes == artifact.size_bytes
    store = loop.runtime.store.root
    assert sorted(store.rglob(f"{name}*")) == [path]  # no second copy
    assert not list(store.rglob("*.part"))  # the dead copy's part is gone too
    eeg = httpx.get(
        f"{loop.url('eeg')}/recordings", headers={"X-Service-Token": TOKEN}, timeout=30
    ).json()
    stored = [r for r in eeg if r["filename"] == f"live-run-{run_id}-calibration.bdf"]
    assert [r["sha256"] for r in stored] == [recording.sha256]  # one recording in the EEG too
    folder = loop.data_dir / "eeg" / "live_recordings" / f"live-run-{run_id}-calibration"
    assert not folder.exists()  # finalised, nothing left to finalise again
    return recording, follow_ups[0].id
