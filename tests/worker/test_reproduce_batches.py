"""``reproduce`` jobs whose children hold lockstep batches (``reproduce_batch``): the children
a config makes, the same records as one-run children, a worker SIGKILLed mid-batch resuming
every run, and cancel in stage 2 and stage 3. The platform tests share two workers and run
in file order (the SIGKILL test is last)."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import select

from services.core.db.models import Artifact, Job
from services.learner.pool import checkpoint_path
from services.learner.runs import RunFailure, RunRecord, run_lockstep
from services.learner.specs import RunSpec
from services.platform.jobs import REPRODUCE_BATCH, REPRODUCE_RUN
from services.worker.reproduce import child_configs, child_outcomes
from tests.worker.conftest import TINY_PPO, Platform

SWEEP = {
    "seeds": 1, "first_seed": 4, "tasks": ["sssg"],
    "methods": ["rl_sparse", "rl_rich", "hf_sparse"], "accuracies": [0.7], "n_labels": 200,
    "ppo": {**TINY_PPO, "total_steps": 512},
}  # fmt: skip
"""Three runs of one PPO shape (one lockstep batch), one with stage 2."""


def _key(record: dict[str, Any]) -> tuple[Any, ...]:
    """The key of the run a record (or a child job's entry of one) is of."""
    return RunSpec.from_dict(record["spec"]).key


def _fields(record: dict[str, Any]) -> dict[str, Any]:
    """A run's record without its wall times (a batch's, not the run's)."""
    fields = {k: v for k, v in record.items() if k != "wall_seconds"}
    if fields.get("hf") is not None:
        fields["hf"] = {k: v for k, v in fields["hf"].items() if k != "wall_seconds"}
    return fields


def test_batch_runs_splits_the_runs_into_lockstep_batches() -> None:
    kind, configs = child_configs({**SWEEP, "batch_runs": 1, "checkpoint_every": 3})
    assert kind == REPRODUCE_RUN.name and len(configs) == 3
    assert all(c["checkpoint_every"] == 3 and "task" in c for c in configs)
    kind, configs = child_configs({**SWEEP, "batch_runs": 2})
    assert kind == REPRODUCE_BATCH.name
    assert [len(c["runs"]) for c in configs] == [2, 1]  # dealt round-robin, at most 2
    methods = sorted(run["method"] for c in configs for run in c["runs"])
    assert methods == ["hf_sparse", "rl_rich", "rl_sparse"]
    kind, configs = child_configs(SWEEP)  # the default, 8: one batch
    assert kind == REPRODUCE_BATCH.name and [len(c["runs"]) for c in configs] == [3]


def test_a_batch_child_gives_its_records_and_names_each_missing_run() -> None:
    _, [config] = child_configs(SWEEP)
    specs = [RunSpec.from_dict(run) for run in config["runs"]]
    crash = RunFailure.from_exception(specs[1], RuntimeError("diverged"))
    child = Job(kind=REPRODUCE_BATCH.name, config=config, status="failed", error="1 of 3")
    child.result = {"runs": [], "failed": [crash.to_dict()]}
    records, failures = child_outcomes(child)
    assert records == [] and [f.label for f in failures] == [s.label for s in specs]
    assert failures[1].message == "diverged"  # the run's own failure
    assert failures[0].error_type == failures[2].error_type == "job failed"


# ---------------------------------------------------------------- through real workers


@pytest.fixture(scope="module")
def workers(fs_platform: Platform) -> list:
    return [fs_platform.start_worker("b1"), fs_platform.start_worker("b2")]


def children(platform: Platform, parent: str) -> list[Job]:
    with platform.sessions() as session:
        return list(session.scalars(select(Job).where(Job.parent_id == parent)).all())


def results_json(platform: Platform, job: Job) -> dict[str, Any]:
    with platform.sessions() as session:
        row = session.get(Artifact, job.result["artifacts"]["results.json"])
        assert row is not None
    return json.loads((platform.settings.resolved_artifact_dir / row.relpath).read_text())


@pytest.mark.slow
def test_a_batch_gives_the_records_of_its_runs_alone(fs_platform: Platform, workers: list) -> None:
    alone = fs_platform.submit("reproduce", {**SWEEP, "batch_runs": 1})
    batched = fs_platform.submit("reproduce", {**SWEEP, "batch_runs": 4})
    done = {
        job_id: fs_platform.wait(job_id, {"succeeded", "failed"}, timeout=300)
        for job_id in (alone, batched)
    }
    for job in done.values():
        assert job.status == "succeeded", job.error
        assert job.result["runs"] == job.result["succeeded"] == 3 and job.progress == 1.0
    assert [c.kind for c in children(fs_platform, alone)] == [REPRODUCE_RUN.name] * 3
    [batch] = children(fs_platform, batched)
    assert batch.kind == REPRODUCE_BATCH.name and batch.status == "succeeded"
    assert batch.steps_done == 3 * 512 and batch.resumed_from_step is None
    # the parent's records: the same runs, field for field but the wall time
    by_key = {
        job_id: {
            RunRecord.from_dict(run).run_spec.key: _fields(run)
            for run in results_json(fs_platform, job)["runs"]
        }
        for job_id, job in done.items()
    }
    assert by_key[alone] == by_key[batched] and len(by_key[alone]) == 3
    # each run of the batch stored its policies, the same weights as its run alone
    singles = {_key(c.result): c for c in children(fs_platform, alone)}
    for entry in batch.result["runs"]:
        single = singles[_key(entry)]
        assert entry["weights_sha256"] == single.result["weights_sha256"]
        assert entry["last_weights_sha256"] == single.result["last_weights_sha256"]
        with fs_platform.sessions() as session:
            model = session.get(Artifact, entry["model_artifact_ids"]["torchscript"])
            assert model is not None and model.job_id == batch.id and model.kind == "model"
    folder = fs_platform.settings.resolved_artifact_dir / f"checkpoint/job-{batch.id}"
    assert sorted(p.suffix for p in folder.iterdir()) == [".json"] * 3  # checkpoints deleted


def _batch_of(platform: Platform, parent: str, until: Any, timeout: float = 120) -> Job:
    """The parent's one batch child, once ``until(child)``."""
    job = platform.wait(parent, lambda job: len(children(platform, parent)) == 1, timeout)
    [child] = children(platform, job.id)
    return platform.wait(child.id, until, timeout, poll=0.05)


def _cancel(platform: Platform, parent: str, child: str) -> None:
    """What ``POST /jobs/{parent}/cancel`` does to a running parent and its running child."""
    platform.set(parent, cancel_requested=True)
    platform.set(child, cancel_requested=True)


@pytest.mark.slow
def test_cancel_stops_a_batch_in_stage_2(fs_platform: Platform, workers: list) -> None:
    config = {**SWEEP, "methods": ["hf_sparse"], "accuracies": [0.6, 0.7], "n_labels": 20_000}
    parent = fs_platform.submit("reproduce", {**config, "ppo": {**TINY_PPO}})
    child = _batch_of(fs_platform, parent, lambda job: job.status == "running")
    # past loading the map's oracle (not interruptible), into the 20,000-label collections,
    # which take far longer than this
    time.sleep(2.0)
    _cancel(fs_platform, parent, child.id)
    child = fs_platform.wait(child.id, {"cancelled", "failed", "succeeded"}, timeout=60)
    assert child.status == "cancelled"
    assert child.steps_done == 0  # stopped in stage 2, before PPO's first step
    assert fs_platform.wait(parent, {"cancelled", "failed", "succeeded"}).status != "succeeded"


@pytest.mark.slow
def test_cancel_stops_a_batch_in_stage_3(fs_platform: Platform, workers: list) -> None:
    config = {
        **SWEEP,
        "methods": ["rl_sparse", "rl_rich"],
        "ppo": {**TINY_PPO, "total_steps": 200_000},
    }
    parent = fs_platform.submit("reproduce", config)
    child = _batch_of(fs_platform, parent, lambda job: job.steps_done > 0)
    _cancel(fs_platform, parent, child.id)
    child = fs_platform.wait(child.id, {"cancelled", "failed", "succeeded"}, timeout=60)
    assert child.status == "cancelled"
    assert 0 < child.steps_done < 2 * 200_000
    assert fs_platform.wait(parent, {"cancelled", "failed", "succeeded"}).status != "succeeded"


@pytest.mark.slow
def test_sigkill_mid_batch_resumes_every_run(fs_platform: Platform, workers: list) -> None:
    steps = 8192  # long enough to be caught mid-batch (progress is written every second)
    config = {
        **SWEEP, "methods": ["rl_sparse", "rl_rich"], "checkpoint_every": 2,
        "ppo": {**TINY_PPO, "total_steps": steps},
    }  # fmt: skip
    parent = fs_platform.submit("reproduce", config)
    child = _batch_of(fs_platform, parent, lambda job: job.status == "running")
    folder = fs_platform.settings.resolved_artifact_dir / f"checkpoint/job-{child.id}"
    specs = [RunSpec.from_dict(run) for run in child.config["runs"]]
    checkpoints = [checkpoint_path(folder, spec) for spec in specs]

    def checkpointed(job: Job) -> bool:  # every run has a checkpoint, past the first
        return job.steps_done >= 2 * 512 and all(Path(p).exists() for p in checkpoints)

    job = fs_platform.wait(child.id, checkpointed, timeout=120, poll=0.05)
    owner = job.lease_owner
    assert owner is not None
    killed = next(p for p in workers if owner.endswith(f"-{p.pid}"))
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()
    workers.append(fs_platform.start_worker("b3"))
    done = fs_platform.wait(parent, {"succeeded", "failed"}, timeout=240)
    assert done.status == "succeeded", done.error
    child = fs_platform.job(child.id)
    assert child.attempts == 2
    assert child.resumed_from_step is not None and 0 < child.resumed_from_step < 2 * steps
    # every run ends as the same runs trained in one uninterrupted batch
    reference = run_lockstep(specs)
    assert all(isinstance(r, RunRecord) for r in reference)
    expected = {
        r.run_spec.key: json.loads(json.dumps(_fields(r.to_dict())))  # type: ignore[union-attr]
        for r in reference
    }
    got = {_key(run): _fields(run) for run in results_json(fs_platform, done)["runs"]}
    assert got == expected and len(got) == 2
