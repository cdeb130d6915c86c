"""An ``eeg_calibration`` job run by the worker's job runner (in this process, no broker):
the recording is read from the artifact store, the classifier's files become artifacts of
the job and a ``classifiers`` row links them to the recording and its subject."""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest

from services.core.artifacts import sha256_file
from services.core.db.base import utcnow
from services.core.db.migrate import upgrade_database
from services.core.db.models import Artifact, Classifier, Job, LabSession, Recording, Subject
from services.core.queue import make_celery
from services.eeg.recordings.io import write_bdf
from services.eeg.virtual.subject import SyntheticRecording
from services.worker.calibration import eeg_calibration
from services.worker.runtime import Runtime, run_job
from services.worker.settings import WorkerSettings

pytestmark = pytest.mark.slow


@pytest.fixture
def runtime(tmp_path: Path) -> Runtime:
    settings = WorkerSettings(data_dir=tmp_path / "data", job_lease_s=30, job_heartbeat_s=0.5)
    upgrade_database(settings.resolved_database_url)
    return Runtime(settings=settings, celery=make_celery(settings))


def store_recording(runtime: Runtime, tmp_path: Path) -> int:
    labels = (np.random.default_rng(0).random(60) > 0.3).tolist()
    path = write_bdf(SyntheticRecording(labels, quality=0.8, seed=0), tmp_path / "cal.bdf")
    stored = runtime.store.put_file(path, kind="recording", name="cal.bdf")
    with runtime.sessions() as session:
        subject = Subject(code="S-007")
        session.add(subject)
        session.flush()
        start = utcnow()
        lab_session = LabSession(
            subject_id=subject.id,
            kind="calibration",
            scheduled_at=start,
            duration_minutes=30,
            ends_at=start + timedelta(minutes=30),
        )
        artifact = Artifact(
            kind="recording",
            relpath=stored.relpath,
            sha256=stored.sha256,
            size_bytes=stored.size_bytes,
        )
        session.add_all([lab_session, artifact])
        session.flush()
        recording = Recording(
            session_id=lab_session.id,
            artifact_id=artifact.id,
            filename="cal.bdf",
            sha256=stored.sha256,
            size_bytes=stored.size_bytes,
        )
        session.add(recording)
        session.commit()
        return recording.id


def add_job(runtime: Runtime, config: dict) -> str:
    with runtime.sessions() as session:
        job = Job(kind="eeg_calibration", config=config)
        session.add(job)
        session.commit()
        return job.id


def test_calibration_job_stores_the_classifier(runtime: Runtime, tmp_path: Path) -> None:
    recording_id = store_recording(runtime, tmp_path)
    config = {"recording_id": recording_id, "seed": 1, "max_passes": 2, "onnx": False}
    job_id = add_job(runtime, {**config, "report": False})
    assert run_job(runtime, job_id, eeg_calibration) == "succeeded"
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
        classifier = session.get(Classifier, job.result["classifier_id"])
        model = session.get(Artifact, job.model_artifact_id)
    assert job.status == "succeeded" and job.attempts == 1
    assert set(job.result["artifacts"]) == {
        "classifier.json", "history.json", "metrics.json", "model.pt", "model.torchscript.pt",
        "model.pt2",
    }  # fmt: skip
    assert classifier.recording_id == recording_id and classifier.job_id == job_id
    assert classifier.torchscript_artifact_id == job.model_artifact_id
    assert (
        classifier.pt2_artifact_id
        == job.model_pt2_artifact_id
        == job.result["artifacts"]["model.pt2"]
    )
    assert classifier.onnx_artifact_id is job.model_onnx_artifact_id is None  # onnx: False
    assert classifier.metrics["n_epochs"] == 60
    assert model.sha256 == sha256_file(runtime.store.path(model.relpath))


def test_calibration_job_refuses_an_unknown_recording(runtime: Runtime) -> None:
    job_id = add_job(runtime, {"recording_id": 999})
    assert run_job(runtime, job_id, eeg_calibration) == "failed"
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
    assert (job.error, job.attempts) == ("recording_id: no recording 999", 1)
