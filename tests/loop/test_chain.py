"""The accelerated chain through the real services on loopback: calibration (virtual subject)
-> eeg_calibration -> test -> online session -> HF model, with every row persisted."""

from __future__ import annotations

import pytest
from sqlalchemy import func, select

from services.core.db.live import LiveDecision, LiveMarker, LiveModelVersion, LiveRun
from services.core.db.models import Classifier, FeedbackLabel, HFModel, Job, Recording
from services.worker.calibration import eeg_calibration
from services.worker.live_session import live_session
from services.worker.runtime import run_job
from tests.loop.conftest import LoopPlatform

pytestmark = pytest.mark.slow

CALIBRATION = {"accelerated": True, "n_actions": 60, "virtual_quality": 1.0, "seed": 1}


def count(loop: LoopPlatform, model, **where) -> int:
    with loop.runtime.sessions() as db:
        query = select(func.count()).select_from(model)
        for key, value in where.items():
            query = query.where(getattr(model, key) == value)
        return db.scalar(query) or 0


def calibrate(loop: LoopPlatform) -> int:
    """A 60-action calibration session, then its eeg_calibration job; the classifier id."""
    session_id = loop.lab_session("calibration")
    run_id, job_id = loop.live_job(session_id, CALIBRATION)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed"
        assert run.result is not None and run.result["actions"] == 60
        recording = db.get(Recording, run.recording_id)
        assert (
            recording is not None and recording.synthetic and recording.validation_status == "valid"
        )
        follow_up = db.get(Job, run.follow_up_job_id)
        assert follow_up is not None and follow_up.config["recording_id"] == recording.id
        follow_up.config = {**follow_up.config, "max_passes": 5}
        db.commit()
        follow_up_id = follow_up.id
    assert count(loop, LiveMarker, run_id=run_id) == 60
    assert count(loop, LiveDecision, run_id=run_id) == 0
    assert run_job(loop.runtime, follow_up_id, eeg_calibration) == "succeeded"
    with loop.runtime.sessions() as db:
        classifier = db.scalar(select(Classifier).where(Classifier.job_id == follow_up_id))
        assert classifier is not None
        return classifier.id


@pytest.fixture(scope="module")
def classifier_id(loop: LoopPlatform) -> int:
    return calibrate(loop)


def test_online_session_labels_to_its_budget_and_registers_the_hf_model(
    loop: LoopPlatform, classifier_id: int
) -> None:
    session_id = loop.lab_session("online")
    options = {"accelerated": True, "classifier_id": classifier_id, "label_budget": 40,
               "virtual_quality": 1.0}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed", run.error
        assert run.result is not None and run.result["labels"] == 40
        model = db.get(HFModel, run.hf_model_id)
        assert model is not None and model.n_labels == 40 and model.session_id == session_id
        markers = run.result["actions"]
    assert count(loop, FeedbackLabel, session_id=session_id) == 40
    assert count(loop, LiveModelVersion, run_id=run_id) == 40
    assert count(loop, LiveMarker, run_id=run_id) == markers
    assert count(loop, LiveDecision, run_id=run_id) == markers
