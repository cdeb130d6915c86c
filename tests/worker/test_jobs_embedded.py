"""Jobs end to end through real ``bgrl worker`` processes on the embedded platform (SQLite and
the filesystem broker): lifecycle, duplicate delivery, bad config, retries, cancel,
reproduction fan-out, and a worker SIGKILLed mid-job. The tests share two workers and run
in file order (the SIGKILL test is last)."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
import torch

from services.core.artifacts import sha256_file
from services.core.db.models import Artifact, Job
from services.core.queue import enqueue_job
from tests.worker.conftest import TINY_PPO, Platform

pytestmark = pytest.mark.slow

GUIDED = {"task": "SSSG", "method": "rl_sparse", "seed": 3, "ppo": TINY_PPO}


@pytest.fixture(scope="module")
def workers(fs_platform: Platform) -> list:
    return [fs_platform.start_worker("w1"), fs_platform.start_worker("w2")]


def artifact(platform: Platform, artifact_id: str) -> Artifact:
    with platform.sessions() as session:
        row = session.get(Artifact, artifact_id)
        assert row is not None
        return row


def test_guided_ppo_lifecycle_and_duplicate_delivery(fs_platform: Platform, workers: list) -> None:
    job_id = fs_platform.submit("guided_ppo", {**GUIDED, "total_steps": 1024})
    enqueue_job(fs_platform.celery, job_id, "guided_ppo")  # a duplicate message
    job = fs_platform.wait(job_id, {"succeeded", "failed"}, timeout=90)
    assert job.status == "succeeded", job.error
    assert job.attempts == 1  # the duplicate found the job leased or finished: never run twice
    assert job.progress == 1.0
    assert job.steps_done == 1024
    assert [step for step, _ in job.curve] == [0, 256, 512, 768, 1024]
    assert job.result["curve"] == job.curve
    assert job.result["seed"] == 3 and job.result["method"] == "rl_sparse"
    assert job.lease_owner is None and job.finished_at is not None
    model = artifact(fs_platform, job.model_artifact_id)
    path = fs_platform.settings.resolved_artifact_dir / model.relpath
    assert model.kind == "model" and model.sha256 == sha256_file(path)
    extra = {"bgrl_meta.json": ""}
    policy = torch.jit.load(str(path), _extra_files=extra)
    assert policy(torch.zeros(1, 13)).shape == (1, 3)  # normalisation + actor, raw observations
    # the job's model is the best evaluation's policy; the result says which and has the last
    meta = json.loads(extra["bgrl_meta.json"])
    assert job.result["model"] == meta["checkpoint"] == "best"
    assert [job.result["best_step"], job.result["best_spl"]] in job.curve
    assert job.result["best_spl"] == max(spl for _, spl in job.curve) == meta["spl"]
    last = artifact(fs_platform, job.result["last_model_artifact_id"])
    last_path = fs_platform.settings.resolved_artifact_dir / last.relpath
    assert last.kind == "model" and last.id != model.id and last.job_id == job_id
    assert last.sha256 == sha256_file(last_path)
    extra = {"bgrl_meta.json": ""}
    torch.jit.load(str(last_path), _extra_files=extra)
    assert json.loads(extra["bgrl_meta.json"])["checkpoint"] == "last"
    # the same two policies as torch.export programs and ONNX, their descriptions inside
    assert job.result["last_model_artifact_ids"]["torchscript"] == last.id
    for artifact_id, checkpoint_name in [
        (job.model_pt2_artifact_id, "best"),
        (job.result["last_model_artifact_ids"]["pt2"], "last"),
    ]:
        program_path = (
            fs_platform.settings.resolved_artifact_dir / artifact(fs_platform, artifact_id).relpath
        )
        extra = {"bgrl_meta.json": ""}
        program = torch.export.load(str(program_path), extra_files=extra).module()
        assert json.loads(extra["bgrl_meta.json"])["checkpoint"] == checkpoint_name
        assert program(torch.zeros(2, 13)).shape == (2, 3)
    onnx_model = artifact(fs_platform, job.model_onnx_artifact_id)
    assert onnx_model.relpath.endswith("policy.onnx") and onnx_model.job_id == job_id
    checkpoint = artifact(fs_platform, job.checkpoint_artifact_id)
    assert checkpoint.kind == "checkpoint" and checkpoint.relpath.endswith("checkpoint.pt")


def test_bad_config_fails_at_once_naming_the_field(fs_platform: Platform, workers: list) -> None:
    job_id = fs_platform.submit("guided_ppo", {**GUIDED, "total_steps": 512, "max_epoch": 3})
    job = fs_platform.wait(job_id, {"failed", "succeeded"})
    assert job.status == "failed"
    assert job.attempts == 1
    assert job.error == "max_epoch: Extra inputs are not permitted"


def test_failed_attempts_are_bounded_then_retry_succeeds(
    fs_platform: Platform, workers: list
) -> None:
    config = {**GUIDED, "total_steps": 512}
    with fs_platform.sessions() as session:
        job = Job(kind="guided_ppo", config=config, max_attempts=2)
        session.add(job)
        session.commit()
        job_id = job.id
    checkpoint = fs_platform.settings.resolved_artifact_dir / f"checkpoint/job-{job_id}"
    checkpoint.mkdir(parents=True)
    (checkpoint / "checkpoint.pt").write_bytes(b"not a checkpoint")  # every attempt fails
    enqueue_job(fs_platform.celery, job_id, "guided_ppo")
    job = fs_platform.wait(job_id, {"failed", "succeeded"})
    assert job.status == "failed"
    assert job.attempts == 2  # retried once, then given up
    assert job.error.startswith("ValueError: checkpoint: checkpoint.pt is not a readable")
    assert "Traceback" in job.traceback

    (checkpoint / "checkpoint.pt").unlink()
    fs_platform.set(job_id, status="queued", attempts=0, error=None, traceback=None)  # the api
    enqueue_job(fs_platform.celery, job_id, "guided_ppo")
    job = fs_platform.wait(job_id, {"failed", "succeeded"})
    assert job.status == "succeeded", job.error
    assert job.attempts == 1 and job.error is None


def test_cancel_stops_a_running_job_within_5_s(fs_platform: Platform, workers: list) -> None:
    job_id = fs_platform.submit("guided_ppo", {**GUIDED, "total_steps": 200_000})
    fs_platform.wait(job_id, lambda job: job.status == "running" and job.steps_done > 0)
    asked = time.monotonic()
    fs_platform.set(job_id, cancel_requested=True)  # what POST /jobs/{id}/cancel does
    job = fs_platform.wait(job_id, {"cancelled", "failed", "succeeded"}, timeout=10, poll=0.05)
    took = time.monotonic() - asked
    assert job.status == "cancelled"
    assert took < 5.0, f"cancel took {took:.1f} s"
    assert job.lease_owner is None and job.steps_done < 200_000


def test_cancel_stops_hf_label_collection_within_5_s(fs_platform: Platform, workers: list) -> None:
    config = {**GUIDED, "method": "hf_sparse", "accuracy": 0.7, "n_labels": 1000}
    job_id = fs_platform.submit("guided_ppo", {**config, "total_steps": 200_000})
    fs_platform.wait(job_id, lambda job: job.status == "running", poll=0.05)
    # past loading the map's oracle (not interruptible; seconds on a loaded machine), into
    # the 1000-label collection, which takes longer than this
    time.sleep(2.0)
    asked = time.monotonic()
    fs_platform.set(job_id, cancel_requested=True)
    job = fs_platform.wait(job_id, {"cancelled", "failed", "succeeded"}, timeout=10, poll=0.05)
    took = time.monotonic() - asked
    assert job.status == "cancelled"
    assert took < 5.0, f"cancel took {took:.1f} s"
    assert job.steps_done == 0  # stopped in stage 2, before PPO's first step


def test_reproduce_fans_out_and_writes_the_reproduction(
    fs_platform: Platform, workers: list
) -> None:
    config = {
        "seeds": 1,
        "first_seed": 2,
        "tasks": ["sssg"],
        "methods": ["rl_sparse", "rl_rich"],
        "ppo": {**TINY_PPO, "total_steps": 512},
    }
    job_id = fs_platform.submit("reproduce", config)
    job = fs_platform.wait(job_id, {"succeeded", "failed"}, timeout=120)
    assert job.status == "succeeded", job.error
    assert job.result["runs"] == 2 and job.result["succeeded"] == 2
    assert job.result["failed"] == []
    names = set(job.result["artifacts"])
    assert {"results.json", "results.csv", "summary.md", "summary.json"} <= names
    assert any(name.endswith(".png") for name in names)
    results = artifact(fs_platform, job.result["artifacts"]["results.json"])
    data = json.loads((fs_platform.settings.resolved_artifact_dir / results.relpath).read_text())
    assert sorted(run["method"] for run in data["runs"]) == ["rl_rich", "rl_sparse"]
    assert data["config"]["job"]["id"] == job_id
    assert data["failed"] == []


def test_sigkill_mid_job_resumes_from_checkpoint_with_the_same_result(
    fs_platform: Platform, workers: list
) -> None:
    config = {**GUIDED, "seed": 5, "total_steps": 4096, "checkpoint_every": 2}
    reference = fs_platform.submit("guided_ppo", config)
    victim = fs_platform.submit("guided_ppo", config)

    def checkpointed(job) -> bool:
        return job.checkpoint_artifact_id is not None and job.steps_done >= 768

    job = fs_platform.wait(victim, checkpointed, timeout=90, poll=0.05)
    owner = job.lease_owner
    assert owner is not None
    killed = next(p for p in workers if owner.endswith(f"-{p.pid}"))
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()
    assert fs_platform.job(victim).status == "running"  # the row still says so: lease pending

    replacement = fs_platform.start_worker("w3")
    workers.append(replacement)
    done = fs_platform.wait(victim, {"succeeded", "failed"}, timeout=120)
    ref = fs_platform.wait(reference, {"succeeded", "failed"}, timeout=120)
    assert done.status == ref.status == "succeeded", (done.error, ref.error)
    assert done.attempts == 2
    assert done.resumed_from_step is not None and 0 < done.resumed_from_step < config["total_steps"]
    assert done.resumed_from_step % 256 == 0  # a checkpoint every 2 updates of 128 steps
    for key in ("curve", "final_spl", "n_episodes", "training_episodes", "weights_sha256"):
        assert done.result[key] == ref.result[key], key
    assert done.curve == ref.curve
