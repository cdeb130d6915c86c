"""Data a lab keeps (issue 10): a subject's sessions exported as BIDS and read back with
mne-bids; an online session replayed through the live decoder and the learner with the same
classifier reproduces its labels and its pi_HF."""

from __future__ import annotations

import csv
import json
import zipfile
from pathlib import Path

import mne_bids
import numpy as np
import pytest
import torch
from sqlalchemy import select

from services.core.db.live import LiveDecision, LiveMarker, LiveRun
from services.core.db.models import Artifact, FeedbackLabel, HFModel, Job, LabSession
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.worker.bids import ACTION_EVENT_ID, bids_export, export_subject
from services.worker.live_session import live_session
from services.worker.replay import session_replay
from services.worker.runtime import run_job
from tests.loop.conftest import LoopPlatform
from tests.loop.test_chain import calibrate

pytestmark = pytest.mark.slow

SUBJECT = "S-002"
LABELS = 15
HF_METHOD = "paper"
"""The online session's stage-2 method, chosen by the lab (not the recommended one)."""


@pytest.fixture(scope="module")
def online(loop: LoopPlatform) -> dict[str, int]:
    """A calibration session, its classifier and an accelerated online session."""
    classifier_id = calibrate(loop)
    with loop.runtime.sessions() as db:  # the calibration session belongs to S-001
        subject_id = db.scalar(select(LabSession.subject_id).order_by(LabSession.id.desc()))
    session_id = loop.lab_session("online", subject_code=SUBJECT)
    options = {"accelerated": True, "classifier_id": classifier_id, "label_budget": LABELS,
               "virtual_quality": 0.6, "seed": 3, "hf_method": HF_METHOD,
               "label_channel": "hard"}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    return {"classifier_id": classifier_id, "session_id": session_id, "run_id": run_id,
            "calibration_subject_id": subject_id}  # fmt: skip


def _job(loop: LoopPlatform, kind: str, config: dict) -> str:
    with loop.runtime.sessions() as db:
        job = Job(kind=kind, config=config, status="queued")
        db.add(job)
        db.commit()
        return job.id


def test_replay_with_the_same_classifier_reproduces_the_labels(
    loop: LoopPlatform, online: dict[str, int]
) -> None:
    session_id = online["session_id"]
    job_id = _job(loop, "session_replay", {"session_id": session_id})
    assert run_job(loop.runtime, job_id, session_replay) == "succeeded"
    with loop.runtime.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None and job.result is not None
        result = job.result
        original = {
            row.step: row
            for row in db.scalars(
                select(FeedbackLabel).where(FeedbackLabel.session_id == session_id)
            )
        }
        decisions = db.scalars(
            select(LiveDecision).where(LiveDecision.run_id == online["run_id"])
        ).all()
        model = db.get(HFModel, result["hf_model_id"])
        assert model is not None
        run = db.get(LiveRun, online["run_id"])
        assert run is not None
        first = db.get(HFModel, run.hf_model_id)
        assert first is not None
        assert run.hf_method == first.metrics["hf_method"] == HF_METHOD != RECOMMENDED_METHOD
        assert model.metrics["hf_method"] == HF_METHOD
        paths = [
            loop.runtime.store.path(
                db.scalar(select(Artifact.relpath).where(Artifact.id == m.torchscript_artifact_id))
            )
            for m in (first, model)
        ]
    assert len(original) == LABELS
    replayed = {label["step"]: label for label in result["labels"]}
    assert sorted(replayed) == sorted(original)
    for step, label in original.items():
        assert replayed[step]["feedback"] == ("error" if label.decoded_error else "correct")
        assert replayed[step]["p_error"] == pytest.approx(label.p_error, abs=1e-5)
    comparison = result["comparison"]
    assert comparison["decisions_compared"] == len(decisions)
    assert comparison["decisions_agreeing"] == len(decisions)
    assert model.session_id == session_id and model.n_labels == LABELS
    assert model.metrics["replay_of_session"] == session_id
    assert comparison["hf_policy_spl"] == comparison["original_hf_policy_spl"]
    # The same labels train the same Fhat: both exported policies give the same logits.
    obs = torch.tensor(np.random.default_rng(0).uniform(0, 3, (32, 13)), dtype=torch.float32)
    first_logits, replay_logits = (torch.jit.load(str(p))(obs) for p in paths)
    assert torch.allclose(first_logits, replay_logits, atol=1e-5)


def test_replay_of_a_run_without_its_hf_model_trains_with_the_runs_method(
    loop: LoopPlatform, online: dict[str, int]
) -> None:
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, online["run_id"])
        assert run is not None
        kept_model_id, run.hf_model_id = run.hf_model_id, None  # as if the model were deleted
        db.commit()
    try:
        job_id = _job(loop, "session_replay", {"session_id": online["session_id"]})
        assert run_job(loop.runtime, job_id, session_replay) == "succeeded"
        with loop.runtime.sessions() as db:
            job = db.get(Job, job_id)
            assert job is not None and job.result is not None
            model = db.get(HFModel, job.result["hf_model_id"])
            assert model is not None and model.metrics["hf_method"] == HF_METHOD
    finally:
        with loop.runtime.sessions() as db:
            run = db.get(LiveRun, online["run_id"])
            assert run is not None
            run.hf_model_id = kept_model_id
            db.commit()


def test_replay_refuses_a_calibration_session(loop: LoopPlatform, online: dict[str, int]) -> None:
    with loop.runtime.sessions() as db:
        calibration = db.scalar(select(LabSession.id).where(LabSession.kind == "calibration"))
    job_id = _job(loop, "session_replay", {"session_id": calibration})
    assert run_job(loop.runtime, job_id, session_replay) == "failed"
    with loop.runtime.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None and "calibration session" in (job.error or "")


@pytest.fixture(scope="module")
def soft_online(loop: LoopPlatform, online: dict[str, int]) -> dict[str, int]:
    """An accelerated online session with the same classifier that asks for no label
    channel: the soft one, as the classifier has a calibrated posterior."""
    session_id = loop.lab_session("online", subject_code="S-003")  # S-002's export: 1 session
    options = {"accelerated": True, "classifier_id": online["classifier_id"],
               "label_budget": LABELS, "virtual_quality": 0.6,
               "seed": 3, "hf_method": HF_METHOD}  # fmt: skip
    run_id, job_id = loop.live_job(session_id, options)
    assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    return {"session_id": session_id, "run_id": run_id}


def test_a_soft_channel_session_keeps_each_labels_likelihood_ratio(
    loop: LoopPlatform, soft_online: dict[str, int]
) -> None:
    """The run records its channel; every label keeps its decision's log-likelihood ratio
    (what a label re-sent after a crash is sent with), and a replay, which decodes the
    recording anew on the soft channel, trains the same pi_HF."""
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, soft_online["run_id"])
        assert run is not None and run.status == "completed" and run.label_channel == "soft"
        ratios = {d.step: d.log_likelihood_ratio for d in db.scalars(
            select(LiveDecision).where(LiveDecision.run_id == run.id, LiveDecision.status == "ok")
        )}  # fmt: skip
        labels = db.scalars(
            select(FeedbackLabel).where(FeedbackLabel.session_id == soft_online["session_id"])
        ).all()
        first = db.get(HFModel, run.hf_model_id)
        assert first is not None
    assert len(labels) == LABELS
    assert all(label.log_likelihood_ratio is not None for label in labels)
    assert {label.step: label.log_likelihood_ratio for label in labels} == {
        label.step: ratios[label.step] for label in labels
    }
    assert len({label.log_likelihood_ratio for label in labels}) > 1  # graded, not two values
    job_id = _job(loop, "session_replay", {"session_id": soft_online["session_id"]})
    assert run_job(loop.runtime, job_id, session_replay) == "succeeded"
    with loop.runtime.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None and job.result is not None
        comparison = job.result["comparison"]
    assert comparison["decisions_agreeing"] == comparison["decisions_compared"] > 0
    assert comparison["hf_policy_spl"] == comparison["original_hf_policy_spl"]


def test_the_soft_and_hard_channels_train_different_policies_from_one_classifier(
    loop: LoopPlatform, online: dict[str, int], soft_online: dict[str, int]
) -> None:
    """The channel is not a label on the row only: the learner's Fhat saw other evidence."""
    with loop.runtime.sessions() as db:
        hard_run = db.get(LiveRun, online["run_id"])
        soft_run = db.get(LiveRun, soft_online["run_id"])
        assert hard_run is not None and soft_run is not None
        assert hard_run.label_channel == "hard" and soft_run.label_channel == "soft"
        models = [db.get(HFModel, r.hf_model_id) for r in (hard_run, soft_run)]
        paths = [
            loop.runtime.store.path(
                db.scalar(select(Artifact.relpath).where(Artifact.id == m.torchscript_artifact_id))
            )
            for m in models
            if m is not None
        ]
    assert len(paths) == 2
    obs = torch.tensor(np.random.default_rng(0).uniform(0, 3, (32, 13)), dtype=torch.float32)
    hard_logits, soft_logits = (torch.jit.load(str(p))(obs) for p in paths)
    assert not torch.allclose(hard_logits, soft_logits, atol=1e-4)


def _read_tsv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle, delimiter="\t"))


def test_bids_export_reads_back_with_the_sessions_events_and_labels(
    loop: LoopPlatform, online: dict[str, int], tmp_path: Path
) -> None:
    with loop.runtime.sessions() as db:
        subject_id = db.scalar(
            select(LabSession.subject_id).where(LabSession.id == online["session_id"])
        )
        markers = db.scalars(
            select(LiveMarker)
            .where(LiveMarker.run_id == online["run_id"])
            .order_by(LiveMarker.step)
        ).all()
        decisions = {
            d.step: d
            for d in db.scalars(select(LiveDecision).where(LiveDecision.run_id == online["run_id"]))
        }
    progress: list[tuple[int, int]] = []
    summary = export_subject(
        loop.runtime, int(subject_id), tmp_path / "bids", lambda *at: progress.append(at)
    )
    assert progress == [(0, 1)]  # called before the subject's one session
    assert summary["bids_subject"] == "S002" and summary["synthetic"] is True
    assert [s["session_id"] for s in summary["sessions"]] == [online["session_id"]]

    path = mne_bids.BIDSPath(
        subject="S002", session=str(online["session_id"]), task="online", datatype="eeg",
        root=tmp_path / "bids",
    )  # fmt: skip
    raw = mne_bids.read_raw_bids(path, verbose="error")
    expected = [
        f"{('forward', 'turn_left', 'turn_right')[m.action]}/"
        f"{'correct' if m.oracle_correct else 'error'}"
        for m in markers
    ]
    assert list(raw.annotations.description) == expected
    start = 0.0  # the accelerated virtual stream starts at 0 on the markers' clock
    onsets = np.array([m.eeg_ts - start for m in markers])
    assert np.allclose(raw.annotations.onset, onsets, atol=1.0 / raw.info["sfreq"])
    table = _read_tsv(path.copy().update(suffix="events", extension=".tsv").fpath)
    assert [int(r["step"]) for r in table] == [m.step for m in markers]
    assert [int(r["value"]) for r in table] == [ACTION_EVENT_ID[e] for e in expected]
    for row, marker in zip(table, markers, strict=True):
        decision = decisions[marker.step]
        assert row["decision"] == decision.status
        assert row["decoded_feedback"] == (decision.feedback or "n/a")
        if decision.p_error is None:
            assert row["p_error"] == "n/a"
        else:
            assert float(row["p_error"]) == pytest.approx(decision.p_error, abs=1e-6)
    sidecar = json.loads(path.copy().update(suffix="eeg", extension=".json").fpath.read_text())
    assert sidecar["SyntheticData"] is True
    participants = _read_tsv(tmp_path / "bids" / "participants.tsv")
    assert [(p["participant_id"], p["synthetic"]) for p in participants] == [("sub-S002", "true")]
    description = json.loads((tmp_path / "bids" / "dataset_description.json").read_text())
    assert "synthetic" in description["GeneratedBy"][0]["Description"]


def test_bids_export_job_stores_a_zip_artifact(loop: LoopPlatform, online: dict[str, int]) -> None:
    calibration_subject = online["calibration_subject_id"]
    job_id = _job(loop, "bids_export", {"subject_id": calibration_subject})
    assert run_job(loop.runtime, job_id, bids_export) == "succeeded"
    with loop.runtime.sessions() as db:
        job = db.get(Job, job_id)
        assert job is not None and job.result is not None
        artifact = db.get(Artifact, job.result["artifact_id"])
        assert artifact is not None and artifact.kind == "bids" and artifact.job_id == job_id
        relpath = artifact.relpath
    with zipfile.ZipFile(loop.runtime.store.path(relpath)) as archive:
        names = archive.namelist()
    sessions = job.result["sessions"]
    assert sessions and all(s["source"].startswith("recording") for s in sessions)
    assert "dataset_description.json" in names and "participants.tsv" in names
    assert all(s["path"] in names for s in sessions)


def test_bgrl_bids_export_writes_the_dataset(
    loop: LoopPlatform, online: dict[str, int], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from typer.testing import CliRunner

    from services.cli.main import app

    monkeypatch.setenv("BGRL_DATA_DIR", str(loop.data_dir))
    out = tmp_path / "ds"
    result = CliRunner().invoke(
        app,
        [
            "bids",
            "export",
            "--subject",
            SUBJECT,
            "--out",
            str(out),
            "--zip",
            str(tmp_path / "ds.zip"),
        ],
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert [s["session_id"] for s in summary["sessions"]] == [online["session_id"]]
    assert (out / summary["sessions"][0]["path"]).is_file()
    assert zipfile.ZipFile(tmp_path / "ds.zip").namelist()
    again = CliRunner().invoke(
        app, ["bids", "export", "--subject", "NOBODY", "--out", str(tmp_path / "x")]
    )
    assert again.exit_code == 1 and "no subject with code 'NOBODY'" in again.output
