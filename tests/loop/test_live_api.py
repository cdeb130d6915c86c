"""The live-session routes of the api: start (a live run and its queued job), refusals,
stop, status with counts/accuracy/latency from the rows, events, frames shown."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from services.core.db.live import LiveDecision, LiveMarker, LiveModelVersion, LiveRun
from services.core.db.models import Classifier, FeedbackLabel, Job
from services.worker.live_session import online_label_channel
from tests.api.conftest import Api, make_settings, start_api


@pytest.fixture
def api(tmp_path: Path) -> Iterator[Api]:
    yield from start_api(make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'bgrl.db'}"))


def lab_session(api: Api, kind: str, code: str | None = None) -> int:
    staff = api.as_("staff")
    subject = api.client.post("/api/v1/subjects", json={"code": code or f"S-{kind}"}, headers=staff)
    body = {"subject_id": subject.json()["id"], "kind": kind,
            "scheduled_at": datetime.now(UTC).isoformat()}  # fmt: skip
    response = api.client.post("/api/v1/sessions", json=body, headers=staff)
    assert response.status_code == 201, response.text
    return int(response.json()["id"])


def db(api: Api):
    return api.client.app.state.sessions()  # type: ignore[attr-defined]


def test_start_creates_a_run_and_its_job_and_refuses_bad_starts(api: Api) -> None:
    staff = api.as_("staff")
    cal = lab_session(api, "calibration")
    bad = api.client.post(
        f"/api/v1/sessions/{cal}/start", json={"eeg_source": "lsl"}, headers=staff
    )
    assert bad.status_code == 422 and "stream_name" in bad.text
    viewer = api.client.post(f"/api/v1/sessions/{cal}/start", json={}, headers=api.as_("viewer"))
    assert viewer.status_code == 403
    started = api.client.post(
        f"/api/v1/sessions/{cal}/start", json={"accelerated": True, "n_actions": 60}, headers=staff
    )
    assert started.status_code == 201, started.text
    run = started.json()
    assert (run["mode"], run["status"], run["options"]["n_actions"]) == (
        "calibration",
        "queued",
        60,
    )
    with db(api) as session:
        job = session.get(Job, run["job_id"])
        assert job is not None and job.kind == "live_session" and job.status == "queued"
        assert job.config["run_id"] == run["id"] and job.config["session_id"] == cal
    again = api.client.post(f"/api/v1/sessions/{cal}/start", json={}, headers=staff)
    assert again.status_code == 409
    online = lab_session(api, "online")
    missing = api.client.post(f"/api/v1/sessions/{online}/start", json={}, headers=staff)
    assert missing.json() == {
        "detail": "online sessions need a classifier",
        "field": "classifier_id",
    }
    unknown = api.client.post(
        f"/api/v1/sessions/{online}/start", json={"classifier_id": 9}, headers=staff
    )
    assert unknown.json() == {"detail": "no classifier 9", "field": "classifier_id"}
    bad_method = api.client.post(
        f"/api/v1/sessions/{online}/start", json={"hf_method": "nope"}, headers=staff
    )
    assert bad_method.status_code == 422 and "hf_method" in bad_method.text
    not_online = api.client.post(
        f"/api/v1/sessions/{cal}/start", json={"hf_method": "paper"}, headers=staff
    )
    assert not_online.json() == {
        "detail": "hf_method applies to online sessions, not to a calibration session",
        "field": "hf_method",
    }
    soft_calibration = api.client.post(
        f"/api/v1/sessions/{cal}/start", json={"label_channel": "soft"}, headers=staff
    )
    assert soft_calibration.json() == {
        "detail": "label_channel applies to online sessions, not to a calibration session",
        "field": "label_channel",
    }
    with db(api) as session:  # a classifier from before posteriors were calibrated
        uncalibrated = Classifier(name="old", metrics={"test_accuracy": 0.7})
        session.add(uncalibrated)
        session.commit()
        uncalibrated_id = uncalibrated.id
    soft_old = api.client.post(
        f"/api/v1/sessions/{online}/start",
        json={"classifier_id": uncalibrated_id, "label_channel": "soft"},
        headers=staff,
    )
    assert soft_old.status_code == 422 and soft_old.json()["field"] == "label_channel"
    assert "no calibrated posterior" in soft_old.json()["detail"]
    stopped = api.client.post(f"/api/v1/sessions/{cal}/stop", headers=staff)
    assert stopped.status_code == 200 and stopped.json()["stop_requested"] is True
    never = api.client.post(f"/api/v1/sessions/{online}/stop", headers=staff)
    assert never.status_code == 404


def test_an_online_session_takes_the_soft_channel_if_its_classifier_is_calibrated(
    api: Api,
) -> None:
    """No label_channel asked: the worker's runner takes soft with a calibrated posterior,
    hard without one or with one whose Platt slope is not positive (its soft labels would
    point away from the truth: asked for, it is refused), and a run whose learner session
    was opened keeps its channel."""
    staff = api.as_("staff")
    platt = {"method": "platt", "intercept": -0.4, "prior_error": 0.3, "n_fit": 72}
    with db(api) as session:
        calibrated = Classifier(name="new", metrics={"calibration": {**platt, "slope": 1.2}})
        uncalibrated = Classifier(name="old", metrics={"test_accuracy": 0.7})
        backwards = Classifier(name="backwards", metrics={"calibration": {**platt, "slope": -9.1}})
        session.add_all([calibrated, uncalibrated, backwards])
        session.commit()
        classifiers = [("soft", calibrated.id), ("hard", uncalibrated.id), ("hard", backwards.id)]
        backwards_id = backwards.id
    refused = api.client.post(
        f"/api/v1/sessions/{lab_session(api, 'online', code='S-refused')}/start",
        json={"classifier_id": backwards_id, "label_channel": "soft"},
        headers=staff,
    )
    assert refused.status_code == 422 and refused.json()["field"] == "label_channel"
    assert "Platt slope is -9.1 (fitted on 72 validation epochs)" in refused.json()["detail"]
    for n, (channel, classifier_id) in enumerate(classifiers):
        online = lab_session(api, "online", code=f"S-{channel}-{n}")
        started = api.client.post(
            f"/api/v1/sessions/{online}/start", json={"classifier_id": classifier_id}, headers=staff
        )
        assert started.status_code == 201, started.text
        assert "label_channel" not in started.json()["options"]
        with db(api) as session:
            run = session.get(LiveRun, started.json()["id"])
            assert run is not None
            assert online_label_channel(session, run) == channel
            run.hf_session_id, run.label_channel = "opened-before", "hard"  # a resumed run
            assert online_label_channel(session, run) == "hard"


def test_live_status_events_and_frames_shown(api: Api) -> None:
    staff = api.as_("staff")
    cal = lab_session(api, "calibration")
    run_id = api.client.post(f"/api/v1/sessions/{cal}/start", json={}, headers=staff).json()["id"]
    t0 = datetime(2026, 12, 2, 9, tzinfo=UTC)
    with db(api) as session:
        for step in range(4):
            session.add(
                LiveMarker(
                    run_id=run_id, session_id=cal, step=step, sim_session_id="s", sim_step=step,
                    episode=0, action=0, oracle_correct=step != 1, observation=[0.0] * 13,
                    marker_ts=100.0 + 1.5 * step, eeg_ts=100.0 + 1.5 * step,
                    executed_at=t0 + timedelta(seconds=1.5 * step),
                )
            )  # fmt: skip
            status = "rejected" if step == 3 else "ok"
            feedback = None if step == 3 else ("error" if step in (1, 2) else "correct")
            session.add(
                LiveDecision(
                    run_id=run_id, session_id=cal, step=step, status=status, feedback=feedback,
                    reason="blink" if step == 3 else None, oracle_correct=step != 1,
                    epoch_end_ts=100.8 + 1.5 * step, decided_ts=100.81 + 1.5 * step,
                )
            )  # fmt: skip
        session.add(FeedbackLabel(session_id=cal, step=0, state=[0.0] * 13, action=0))
        session.add(
            LiveModelVersion(run_id=run_id, session_id=cal, step=0, labels=1, model_version=1,
                             updated_ts=100.83, next_ready_ts=100.84)
        )  # fmt: skip
        session.commit()
    shown = {"step": 0, "shown_at": (t0 + timedelta(milliseconds=40)).isoformat()}
    first = api.client.post(f"/api/v1/sessions/{cal}/frames-shown", json=shown, headers=staff)
    assert first.status_code == 201
    twice = api.client.post(f"/api/v1/sessions/{cal}/frames-shown", json=shown, headers=staff)
    assert twice.status_code == 409 and twice.json()["field"] == "step"
    live = api.client.get(f"/api/v1/sessions/{cal}/live", headers=api.as_("viewer")).json()
    assert (live["markers"], live["decisions_accepted"], live["decisions_rejected"]) == (4, 3, 1)
    assert live["running_accuracy"] == pytest.approx(2 / 3)  # step 2 decoded error, was correct
    assert live["labels"] == 1 and live["label_budget"] is None
    latency = live["latency"]
    assert latency["epoch_end_to_decision"]["n"] == 4
    assert latency["epoch_end_to_decision"]["p50_ms"] == pytest.approx(10.0, abs=1e-6)
    assert latency["epoch_end_to_next_action"]["p50_ms"] == pytest.approx(40.0, abs=1e-6)
    assert latency["marker_to_frame_shown"]["p50_ms"] == pytest.approx(40.0, abs=1e-3)
    assert live["pace"]["drift_ms"] == pytest.approx(0.0, abs=1e-6)
    events = api.client.get(
        f"/api/v1/sessions/{cal}/events", params={"kind": "decisions", "since_step": 2, "limit": 1},
        headers=staff,
    ).json()  # fmt: skip
    assert (events["total"], len(events["items"]), events["items"][0]["step"]) == (2, 1, 2)
    with db(api) as session:
        assert session.scalar(select(LiveRun.status).where(LiveRun.id == run_id)) == "queued"
