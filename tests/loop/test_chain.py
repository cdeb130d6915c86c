"""The accelerated chain through the real services on loopback: calibration (virtual subject)
-> eeg_calibration -> test -> online session -> HF model, with every row persisted."""

from __future__ import annotations

import io
import threading
import time

import httpx
import numpy as np
import onnxruntime
import pytest
import torch
from sqlalchemy import func, select, update

from services.core.db.live import LiveDecision, LiveMarker, LiveModelVersion, LiveRun
from services.core.db.models import Classifier, FeedbackLabel, HFModel, Job, Recording
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.worker.calibration import eeg_calibration
from services.worker.live_services import ServiceClient
from services.worker.live_session import live_session
from services.worker.runtime import run_job
from services.worker.training import guided_ppo
from tests.api.conftest import make_settings, start_api
from tests.loop.conftest import TOKEN, LoopPlatform
from tests.worker.conftest import TINY_PPO

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
    with loop.runtime.sessions() as db:  # the ended run released its sim session
        sim_session_id = db.scalar(select(LiveRun.sim_session_id).where(LiveRun.id == run_id))
    gone = httpx.get(
        f"{loop.url('sim')}/sessions/{sim_session_id}",
        headers={"X-Service-Token": TOKEN}, timeout=10,
    )  # fmt: skip
    assert gone.status_code in (404, 410), gone.text
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
               "virtual_quality": 1.0, "label_channel": "hard"}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed", run.error
        assert run.result is not None and run.result["labels"] == 40
        assert run.result["prepared_labels"] == 40  # a hard label's update was prepared
        model = db.get(HFModel, run.hf_model_id)
        assert model is not None and model.n_labels == 40 and model.session_id == session_id
        assert run.hf_method == model.metrics["hf_method"] == RECOMMENDED_METHOD  # the default
        markers = run.result["actions"]
    assert count(loop, FeedbackLabel, session_id=session_id) == 40
    assert count(loop, LiveModelVersion, run_id=run_id) == 40
    # the session's pi_HF downloads through the api as ONNX and acts as its TorchScript file
    settings = make_settings(loop.data_dir, loop.runtime.settings.resolved_database_url)
    for api in start_api(settings):
        url = f"/api/v1/hf-models/{model.id}/download"
        files = {
            fmt: api.client.get(url, params={"format": fmt}, headers=api.as_("viewer"))
            for fmt in ("onnx", "torchscript")
        }
    assert all(response.status_code == 200 for response in files.values())
    observations = np.random.default_rng(0).normal(0, 2, (32, 13)).astype(np.float32)
    onnx = onnxruntime.InferenceSession(files["onnx"].content)
    (onnx_logits,) = onnx.run(["logits"], {"obs": observations})
    scripted = torch.jit.load(io.BytesIO(files["torchscript"].content))
    with torch.no_grad():
        logits = scripted(torch.from_numpy(observations)).numpy()
    assert np.abs(onnx_logits - logits).max() < 1e-5
    assert count(loop, LiveMarker, run_id=run_id) == markers
    assert count(loop, LiveDecision, run_id=run_id) == markers

    # one call starts guided PPO from the session's HF model
    with loop.runtime.sessions() as db:
        job = Job(
            kind="guided_ppo",
            config={"task": "sssg", "method": "hf_sparse", "hf_model_id": model.id, "seed": 0,
                    "ppo": TINY_PPO, "total_steps": 512},
        )  # fmt: skip
        db.add(job)
        db.commit()
        guided_id = job.id
    assert run_job(loop.runtime, guided_id, guided_ppo) == "succeeded"
    with loop.runtime.sessions() as db:
        guided = db.get(Job, guided_id)
        assert guided is not None and guided.result is not None
        assert guided.result["method"] == "hf_sparse"
        assert guided.result["accuracy"] == round(model.feedback_accuracy, 4)
        assert guided.result["hf_policy_spl"] == model.metrics["hf_policy_spl"]


def test_a_prepare_that_fails_does_not_stop_the_session(
    loop: LoopPlatform, classifier_id: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    def refused(self, method: str, path: str, **kwargs: object) -> None:
        raise httpx.ConnectError(f"{method} {path}: refused for the test")

    monkeypatch.setattr(ServiceClient, "call_once", refused)
    session_id = loop.lab_session("online")
    options = {"accelerated": True, "classifier_id": classifier_id, "label_budget": 8,
               "virtual_quality": 1.0}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed" and run.result is not None
        assert (run.result["labels"], run.result["prepared_labels"]) == (8, 0)
    assert count(loop, FeedbackLabel, session_id=session_id) == 8


def test_test_session_reports_the_live_accuracy_against_the_oracle(
    loop: LoopPlatform, classifier_id: int
) -> None:
    session_id = loop.lab_session("test")
    options = {"accelerated": True, "classifier_id": classifier_id, "n_actions": 20}
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.result is not None and run.status == "completed"
        rows = db.execute(
            select(LiveDecision.status, LiveDecision.feedback, LiveDecision.oracle_correct).where(
                LiveDecision.run_id == run_id
            )
        ).all()
    accepted = [r for r in rows if r.status == "ok"]
    hits = sum((r.feedback == "correct") == r.oracle_correct for r in accepted)
    assert (run.result["actions"], run.result["decisions"]) == (20, 20)
    assert run.result["accepted"] == len(accepted)
    assert run.result["accuracy"] == (hits / len(accepted) if accepted else None)
    assert count(loop, FeedbackLabel, session_id=session_id) == 0


def wait_for(check, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


@pytest.mark.parametrize("service", ["sim", "eeg", "learner"])
def test_a_service_killed_mid_session_loses_at_most_one_label(
    loop: LoopPlatform, classifier_id: int, service: str
) -> None:
    session_id = loop.lab_session("online")
    options = {"accelerated": True, "classifier_id": classifier_id, "label_budget": 24,
               "virtual_quality": 1.0}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    outcome: list[str] = []
    worker = threading.Thread(
        target=lambda: outcome.append(run_job(loop.runtime, job_id, live_session))
    )
    worker.start()
    wait_for(lambda: count(loop, FeedbackLabel, session_id=session_id) >= 8)
    loop.kill(service)
    loop.start(service)
    worker.join(timeout=600)
    # A request the kill cut mid-flight (a sim step sent, its answer lost) has an unknown
    # outcome: it is never repeated blindly, the attempt ends and the job is queued again,
    # and the next attempt (a worker's, here the test's) resumes the run from its rows.
    if outcome == ["queued"]:
        outcome.append(run_job(loop.runtime, job_id, live_session))
    assert outcome[-1] == "succeeded", outcome
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed" and run.result is not None
        lost = run.result["decoding_lost"]
        markers = run.result["actions"]
    assert lost <= 1
    assert count(loop, FeedbackLabel, session_id=session_id) == 24
    assert count(loop, LiveDecision, run_id=run_id) == markers
    if service == "eeg":  # the epoch in flight when the ingest broke is the lost one
        assert lost == 1


def test_a_resumed_run_continues_from_its_rows_and_stops_on_command(
    loop: LoopPlatform, classifier_id: int
) -> None:
    """A job stopped mid-session (as a dead worker's is) and claimed again resumes from
    its rows: the step in flight is recorded as lost, nothing is counted twice; a stop
    request then ends the session normally (HF model exported)."""
    session_id = loop.lab_session("online")
    options = {"accelerated": True, "classifier_id": classifier_id, "label_budget": 1000,
               "virtual_quality": 1.0}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    outcome: list[str] = []
    worker = threading.Thread(
        target=lambda: outcome.append(run_job(loop.runtime, job_id, live_session))
    )
    worker.start()
    wait_for(lambda: count(loop, FeedbackLabel, session_id=session_id) >= 5)
    with loop.runtime.sessions() as db:
        db.execute(update(Job).where(Job.id == job_id).values(cancel_requested=True))
        db.commit()
    worker.join(timeout=120)
    assert outcome == ["cancelled"]
    before = count(loop, LiveMarker, run_id=run_id)
    with loop.runtime.sessions() as db:
        db.execute(
            update(Job)
            .where(Job.id == job_id)
            .values(status="queued", cancel_requested=False, attempts=0, finished_at=None)
        )
        db.commit()
    worker = threading.Thread(
        target=lambda: outcome.append(run_job(loop.runtime, job_id, live_session))
    )
    worker.start()
    wait_for(lambda: count(loop, LiveMarker, run_id=run_id) >= before + 5)
    with loop.runtime.sessions() as db:
        db.execute(update(LiveRun).where(LiveRun.id == run_id).values(stop_requested=True))
        db.commit()
    worker.join(timeout=300)
    assert outcome == ["cancelled", "succeeded"]
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "stopped" and run.resumes == 1
        assert run.result is not None and run.result["stopped_on_command"] is True
        assert run.hf_model_id is not None
        markers = run.result["actions"]
        steps = db.scalars(select(LiveMarker.step).where(LiveMarker.run_id == run_id)).all()
    assert sorted(steps) == list(range(markers))
    assert count(loop, LiveDecision, run_id=run_id) == markers
    assert run.result["decoding_lost"] <= 1
