"""Jobs as lab staff and operators meet them: a stored config that is malformed or names a
file gone from the artifact store, retry of a reproduction and two retries at once, and a
checkpoint downloaded while its job rewrites it. One api (SQLite, embedded broker) and the
worker's job runner in this process on the same data folder, shared by the module."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
import threading
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import mne
import mne_bids
import numpy as np
import pytest

from services.core.db.models import (
    Artifact,
    Classifier,
    HFModel,
    Job,
    LabSession,
    Recording,
    Subject,
)
from services.core.files import write_bytes_atomic
from services.core.queue import make_celery
from services.worker.app import load_handler
from services.worker.bids import export_subject
from services.worker.runtime import JobConfigError, Runtime, run_job
from services.worker.session_data import load_classifier
from services.worker.settings import WorkerSettings
from tests.api.conftest import Api, _pg_schema_url, make_settings, start_api
from tests.api.test_jobs import broker_messages
from tests.helpers import fast_password_hashing
from tests.worker.conftest import TINY_PPO

GUIDED = {"task": "SSSG", "method": "rl_sparse", "seed": 1, "total_steps": 256, "ppo": TINY_PPO}


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Api, Runtime]]:
    """The api and a worker runtime sharing one database, broker and artifact store."""
    root = tmp_path_factory.mktemp("outside-use")
    url = f"sqlite:///{root / 'bgrl.db'}"
    with pytest.MonkeyPatch.context() as monkeypatch:
        fast_password_hashing(monkeypatch)
        api_iter = start_api(make_settings(root / "data", url))
        api = next(api_iter)
    settings = WorkerSettings(
        data_dir=root / "data", database_url=url, job_lease_s=30, job_heartbeat_s=0.5
    )
    runtime = Runtime(settings=settings, celery=make_celery(settings))
    try:
        yield api, runtime
    finally:
        runtime.engine.dispose()
        next(api_iter, None)


def add_job(runtime: Runtime, kind: str, config: Any, **values: Any) -> str:
    with runtime.sessions() as session:
        job = Job(kind=kind, config=config, **{"max_attempts": 3, **values})
        session.add(job)
        session.commit()
        return job.id


def row(runtime: Runtime, job_id: str) -> Job:
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
        assert job is not None
        return job


def run(runtime: Runtime, job_id: str) -> str:
    return run_job(runtime, job_id, load_handler(row(runtime, job_id).kind))


def stored_file(runtime: Runtime, data: bytes, kind: str, name: str) -> tuple[str, Path]:
    """A file in the artifact store and its Artifact row: (artifact id, path)."""
    stored = runtime.store.put_bytes(data, kind=kind, name=name)
    with runtime.sessions() as session:
        artifact = Artifact(
            kind=kind, relpath=stored.relpath, sha256=stored.sha256, size_bytes=stored.size_bytes
        )
        session.add(artifact)
        session.commit()
        return artifact.id, runtime.store.path(stored.relpath)


@pytest.mark.parametrize(
    ("config", "error"),
    [
        ([1, 2], "config must be a JSON object of settings, not list"),
        ("task=SSSG", "config must be a JSON object of settings, not str"),
        (
            {**GUIDED, "ppo": {"n_epochs": "four"}},
            "ppo.n_epochs: Input should be a valid integer, not 'four'",
        ),
        (
            {**GUIDED, "ppo": {"hidden_sizes": [32, "x"]}},
            "ppo.hidden_sizes.1: Input should be a valid integer, not 'x'",
        ),
        (
            {**GUIDED, "ppo": {"gamma": 5}},
            "ppo.gamma: Input should be less than or equal to 1, not 5",
        ),
        (
            {**GUIDED, "total_steps": "256"},
            "total_steps: Input should be a valid integer, not '256'",
        ),
        (
            {**GUIDED, "method": "hf_sparse", "accuracy": "0.7"},
            "accuracy: Input should be a valid number, not '0.7'",
        ),
        (
            {**GUIDED, "checkpoint_every": True},
            "checkpoint_every: Input should be a valid integer, not True",
        ),
        ({**GUIDED, "method": "hf_sparse"}, "hf_sparse needs accuracy (or hf_model_id)"),
    ],
)
def test_malformed_stored_config_fails_at_once_naming_the_field(
    lab: tuple[Api, Runtime], config: Any, error: str
) -> None:
    """A config written around the api (an older version, by hand) fails on its first
    attempt with the field named: not an exception out of the task that leaves the job
    ``running`` until its lease expires, nor a TypeError mid-training that is retried."""
    _, runtime = lab
    job_id = add_job(runtime, "guided_ppo", config)
    assert run(runtime, job_id) == "failed"
    job = row(runtime, job_id)
    assert (job.status, job.attempts, job.error) == ("failed", 1, error)
    assert job.lease_owner is None and job.finished_at is not None


def test_hf_model_whose_file_was_removed_fails_naming_hf_model_id(
    lab: tuple[Api, Runtime],
) -> None:
    _, runtime = lab
    artifact_id, path = stored_file(runtime, b"torchscript", "model", "hf.pt")
    with runtime.sessions() as session:
        model = HFModel(name="pi_HF", task="sssg", torchscript_artifact_id=artifact_id)
        session.add(model)
        session.commit()
        hf_model_id = model.id
    path.unlink()  # an operator cleaned the artifact folder
    config = {**GUIDED, "method": "hf_sparse", "accuracy": 0.7, "hf_model_id": hf_model_id}
    job_id = add_job(runtime, "guided_ppo", config)
    assert run(runtime, job_id) == "failed"
    job = row(runtime, job_id)
    assert job.attempts == 1
    assert job.error == (
        f"hf_model_id: the TorchScript file of HF model {hf_model_id} is missing from the "
        "artifact store"
    )


def test_classifier_whose_files_were_removed_is_a_config_error(lab: tuple[Api, Runtime]) -> None:
    """A replay (or live session) given a classifier whose files are gone fails naming
    ``classifier_id`` instead of retrying a FileNotFoundError."""
    _, runtime = lab
    artifact_id, path = stored_file(runtime, b"{}", "classifier", "classifier.json")
    source = add_job(
        runtime, "eeg_calibration", {}, status="succeeded",
        result={"artifacts": {"classifier.json": artifact_id}},
    )  # fmt: skip
    with runtime.sessions() as session:
        classifier = Classifier(name="cal", job_id=source)
        session.add(classifier)
        session.commit()
        classifier_id = classifier.id
    path.unlink()
    with pytest.raises(JobConfigError) as raised:
        load_classifier(runtime, classifier_id)
    assert str(raised.value) == (
        f"classifier_id: file classifier.json of classifier {classifier_id} is missing from the "
        "artifact store"
    )


def test_retry_of_a_reproduction_runs_its_cancelled_and_failed_runs_again(
    lab: tuple[Api, Runtime],
) -> None:
    """Before: the retried parent found every run final and aggregated at once, failing
    again with the same cancelled runs."""
    api, runtime = lab
    parent = add_job(
        runtime, "reproduce", {"quick": True}, status="cancelled", cancel_requested=True
    )
    spec = {"task": "sssg", "method": "rl_sparse", "seed": 0, "ppo_overrides": TINY_PPO}
    runs = {
        status: add_job(
            runtime, "reproduce_run", {**spec, "seed": n}, parent_id=parent, status=status,
            cancel_requested=status == "cancelled", attempts=1,
            error="boom" if status == "failed" else None,
        )
        for n, status in enumerate(("succeeded", "cancelled", "failed"))
    }  # fmt: skip
    broker_messages(api)
    retried = api.client.post(f"/api/v1/jobs/{parent}/retry", headers=api.as_("staff"))
    assert retried.status_code == 200, retried.text
    assert retried.json()["status"] == "queued"
    again = {status: row(runtime, job_id) for status, job_id in runs.items()}
    assert again["succeeded"].status == "succeeded"  # a finished run is kept
    for status in ("cancelled", "failed"):
        job = again[status]
        assert (job.status, job.attempts, job.error, job.cancel_requested) == (
            "queued", 0, None, False,
        )  # fmt: skip
    sent = sorted(args[0] for _, args in broker_messages(api))
    assert sent == sorted([parent, runs["cancelled"], runs["failed"]])
    assert run(runtime, parent) == "waiting"  # for its runs, not aggregated at once


@pytest.fixture
def pg_api(tmp_path: Path) -> Iterator[Api]:
    """The api on PostgreSQL (where requests truly run at once), in a schema of its own."""
    for url in _pg_schema_url():
        with pytest.MonkeyPatch.context() as monkeypatch:
            fast_password_hashing(monkeypatch)
            api_iter = start_api(make_settings(tmp_path / "data", url))
            api = next(api_iter)
        yield api
        next(api_iter, None)


def test_two_retries_at_once_one_wins(pg_api: Api) -> None:
    """Before: each retry read ``failed`` and wrote ``queued``, so several answered 200, the
    job was sent several times and a retry could reset a job a worker had just claimed."""
    api = pg_api
    with api.client.app.state.sessions() as session:
        job = Job(kind="guided_ppo", config=GUIDED, status="failed", attempts=3, error="x")
        session.add(job)
        session.commit()
        job_id = job.id
    barrier = threading.Barrier(6)
    codes: list[int] = []

    def retry() -> None:
        barrier.wait()
        response = api.client.post(f"/api/v1/jobs/{job_id}/retry", headers=api.as_("staff"))
        codes.append(response.status_code)

    threads = [threading.Thread(target=retry) for _ in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(codes) == [200] + [409] * 5
    assert broker_messages(api) == [("bgrl.jobs.guided_ppo", [job_id])]  # sent once
    audit = api.client.get(
        f"/api/v1/audit?action=job.retry&target_id={job_id}", headers=api.as_("admin")
    ).json()
    assert audit["total"] == 1


def test_checkpoint_downloaded_while_its_job_rewrites_it(lab: tuple[Api, Runtime]) -> None:
    """The running job replaces its checkpoint file; the row's checksum follows at the next
    heartbeat. A download in between used to send the new bytes with the old checksum (the
    client's verified download failed); once the file is removed: 410."""
    api, runtime = lab
    artifact_id, path = stored_file(runtime, b"checkpoint at step 256", "checkpoint", "c.pt")
    viewer = api.as_("viewer")
    url = f"/api/v1/artifacts/{artifact_id}/download"
    first = api.client.get(url, headers=viewer)
    assert first.content == b"checkpoint at step 256"
    assert first.headers["x-checksum-sha256"] == hashlib.sha256(first.content).hexdigest()
    write_bytes_atomic(path, b"checkpoint at step 512")  # what the learner does
    second = api.client.get(url, headers=viewer)
    assert second.status_code == 200
    assert second.content == b"checkpoint at step 512"
    assert second.headers["x-checksum-sha256"] == hashlib.sha256(second.content).hexdigest()
    assert 'filename="c.pt"' in second.headers["content-disposition"]
    path.unlink()
    gone = api.client.get(url, headers=viewer)
    assert gone.status_code == 410
    assert gone.json()["detail"] == f"the file of artifact {artifact_id} is missing from the store"


def test_job_model_removed_from_the_store_is_410(lab: tuple[Api, Runtime]) -> None:
    api, runtime = lab
    artifact_id, path = stored_file(runtime, b"policy", "model", "policy.pt")
    job_id = add_job(runtime, "guided_ppo", GUIDED, status="succeeded")
    with runtime.sessions() as session:
        session.get(Job, job_id).model_artifact_id = artifact_id
        session.commit()
    path.unlink()
    response = api.client.get(f"/api/v1/jobs/{job_id}/model", headers=api.as_("viewer"))
    assert response.status_code == 410


@pytest.mark.parametrize("fmt", ["xdf", "brainvision", "eeglab", "edf"])
def test_bids_export_of_a_session_whose_recording_came_from_other_software(
    lab: tuple[Api, Runtime], tmp_path: Path, fmt: str
) -> None:
    """A session's uploaded recording in any format the platform reads is exported as BDF
    with its actions (mne.io.read_raw read it by name: no zip, no XDF, and an EDF's copy)."""
    from tests.eeg.caps import CAP_8, LABELS, virtual_recording
    from tests.eeg.test_formats import (
        CODES,
        SFREQ,
        action_samples,
        write_set,
        write_vhdr,
        xdf_recording,
        zip_files,
    )

    _, runtime = lab
    raw = virtual_recording(SFREQ, CAP_8, seed=4)
    if fmt == "xdf":
        path = xdf_recording(
            raw, tmp_path / "session.xdf", ["correct" if ok else "error" for ok in LABELS]
        )
    elif fmt == "brainvision":
        events = [
            {"onset": int(s), "description": c}
            for s, c in zip(action_samples(raw), CODES, strict=True)
        ]
        write_vhdr(raw, tmp_path, events)
        path = zip_files(sorted(tmp_path.glob("sub01.*")), tmp_path / "sub01.zip")
    elif fmt == "eeglab":
        path = write_set(raw, tmp_path / "session.set")
    else:
        path, plain = tmp_path / "session.edf", raw.copy().pick(CAP_8)
        exg = mne.io.RawArray(  # recorded beside the cap
            plain.get_data(picks=["Cz"]) * 3, mne.create_info(["EXG1"], SFREQ, "misc")
        )
        exg.info["description"] = plain.info["description"]
        plain.add_channels([exg])
        texts = ["correct" if ok else "error" for ok in LABELS]
        plain.set_annotations(mne.Annotations(action_samples(raw) / SFREQ, 0.0, texts))
        mne.export.export_raw(path, plain, fmt="edf", verbose="error")
    artifact_id, stored = stored_file(runtime, path.read_bytes(), "recording", path.name)
    start = datetime(2026, 12, 1, 9, tzinfo=UTC)
    with runtime.sessions() as db:
        subject = Subject(code=f"R-{fmt}")
        db.add(subject)
        db.flush()
        session = LabSession(
            subject_id=subject.id, kind="calibration", scheduled_at=start, duration_minutes=30,
            ends_at=start + timedelta(minutes=30), status="completed",
        )  # fmt: skip
        db.add(session)
        db.flush()
        db.add(
            Recording(
                session_id=session.id, artifact_id=artifact_id, filename=path.name,
                sha256=hashlib.sha256(stored.read_bytes()).hexdigest(),
                size_bytes=stored.stat().st_size, validation_status="valid",
            )
        )  # fmt: skip
        db.commit()
        subject_id, session_id = subject.id, session.id

    summary = export_subject(runtime, subject_id, tmp_path / "bids")
    assert [s["session_id"] for s in summary["sessions"]] == [session_id]
    bids_path = mne_bids.BIDSPath(
        subject=f"R{fmt}", session=str(session_id), task="calibration", datatype="eeg",
        root=tmp_path / "bids",
    )  # fmt: skip
    assert bids_path.fpath.suffix == ".bdf"
    back = mne_bids.read_raw_bids(bids_path, verbose="error")
    assert list(back.annotations.description) == ["correct" if ok else "error" for ok in LABELS]
    np.testing.assert_allclose(
        back.annotations.onset, action_samples(raw) / SFREQ, atol=1.5 / SFREQ
    )
    np.testing.assert_allclose(back.get_data(picks=CAP_8), raw.get_data(picks=CAP_8), atol=2e-7)
    channels = bids_path.copy().update(suffix="channels", extension=".tsv").fpath.read_text()
    types = dict(line.split("\t")[:2] for line in channels.splitlines()[1:])
    assert {types[ch] for ch in CAP_8} == {"EEG"}
    assert types.get("EXG1", "MISC") == "MISC"  # the EDF's EXG channel: MISC, not EEG
    assert ("EXG1" in types) == (fmt == "edf")
    assert bids_errors(tmp_path / "bids") == []


def bids_errors(root: Path) -> list[str]:
    """The BIDS validator's errors on the dataset at ``root`` (its warnings, such as
    recommended fields left out, are not errors); skipped where the validator cannot run."""
    validator = shutil.which("bids-validator-deno") or str(
        Path(sys.executable).with_name("bids-validator-deno")
    )
    if not Path(validator).is_file():
        pytest.skip("bids-validator-deno is not installed (a dev dependency: pip install it)")
    done = subprocess.run(
        [validator, str(root), "--format", "json"], capture_output=True, text=True, timeout=300
    )
    try:
        issues = json.loads(done.stdout)["issues"]["issues"]
    except (ValueError, KeyError):
        pytest.skip(f"bids-validator-deno could not run here: {done.stderr[-500:]}")
    return [
        f"{issue['code']} {issue.get('location', '')}: {issue.get('issueMessage', '')[:200]}"
        for issue in issues
        if issue["severity"] == "error"
    ]
