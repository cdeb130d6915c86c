"""``reproduce`` jobs: the paper's simulated-feedback experiment (Fig. 3) fanned out over the
workers. The parent job creates its child jobs and waits, holding no lease: with
``batch_runs`` > 1 (default 8) one ``reproduce_batch`` job per lockstep batch of at most
``batch_runs`` runs (:func:`services.learner.pool.lockstep_batches`: runs of one PPO shape,
dealt round-robin), with ``batch_runs`` 1 one ``reproduce_run`` job per run. When every
child is final it is sent again and writes what ``bgrl reproduce`` writes (``results.json``,
``results.csv``, ``summary.md``/``summary.json``, the Fig. 3 plots) as artifacts of the job,
from the same run records either way. A failed run is kept as failed with its error; the
others are aggregated and the job ends ``failed`` naming the failed runs.
"""

from __future__ import annotations

import dataclasses
import json
import tempfile
from pathlib import Path
from typing import Any

from sqlalchemy import func, select, update

from services.core.db.models import JOB_FINAL_STATUSES, Job
from services.core.queue import enqueue_job
from services.learner.outputs import Results, load_results, save_results
from services.learner.pool import lockstep_batches
from services.learner.pool import reproduce as write_reproduction
from services.learner.runs import RunFailure, RunRecord
from services.learner.specs import (
    FULL_SEEDS,
    QUICK_SEEDS,
    RunSpec,
    apply_preset,
    build_specs,
)
from services.platform.jobs import REPRODUCE, REPRODUCE_BATCH, REPRODUCE_RUN
from services.platform.jobs.reproduce import ReproduceConfig
from services.worker.runtime import (
    JobConfigError,
    JobContext,
    JobOutcome,
    JobStoppedError,
    parse_config,
)

PLOT_SUFFIXES = (".png",)
RECORD_FIELDS = frozenset(f.name for f in dataclasses.fields(RunRecord))


def specs_from_config(config: dict[str, Any]) -> list[RunSpec]:
    """The run specs of a ``reproduce`` job config (the options of ``bgrl reproduce``)."""
    parsed: ReproduceConfig = parse_config(REPRODUCE, config)
    try:
        treatments, overrides, hf_method = apply_preset(
            parsed.preset, list(parsed.treatments), parsed.ppo.given()
        )
        return build_specs(
            seeds=parsed.seeds or (QUICK_SEEDS if parsed.quick else FULL_SEEDS),
            first_seed=parsed.first_seed,
            tasks=list(parsed.tasks),
            methods=list(parsed.methods),
            accuracies=list(parsed.accuracies),
            treatments=treatments,
            ppo_overrides=overrides,
            hf_method=hf_method,
            n_labels=parsed.n_labels,
        )
    except (TypeError, ValueError) as exc:
        raise JobConfigError(str(exc)) from None


def reproduce(context: JobContext) -> JobOutcome:
    """Handler of ``reproduce`` jobs: fan out the runs, or aggregate them once all are final."""
    with context.runtime.sessions() as session:
        children = session.scalars(
            select(Job).where(Job.parent_id == context.job_id).order_by(Job.created_at)
        ).all()
    if not children:
        return _fan_out(context)
    if any(child.status not in JOB_FINAL_STATUSES for child in children):
        return JobOutcome(wait_for_children=True)  # sent early (a duplicate): keep waiting
    return _aggregate(context, children)


def child_configs(config: dict[str, Any]) -> tuple[str, list[dict[str, Any]]]:
    """The kind and configs of a ``reproduce`` job's children: one run spec each
    (``batch_runs`` 1), or lockstep batches of at most ``batch_runs`` specs."""
    specs = specs_from_config(config)
    every = config.get("checkpoint_every")
    extra = {"checkpoint_every": every} if every else {}
    batch_runs = parse_config(REPRODUCE, config).batch_runs
    if batch_runs == 1:
        return REPRODUCE_RUN.name, [{**spec.to_dict(), **extra} for spec in specs]
    batches = lockstep_batches(specs, workers=1, max_runs=batch_runs)
    return REPRODUCE_BATCH.name, [
        {"runs": [spec.to_dict() for spec in batch.specs], **extra} for batch in batches
    ]


def _fan_out(context: JobContext) -> JobOutcome:
    kind, configs = child_configs(context.config)
    n_runs = sum(len(c["runs"]) if kind == REPRODUCE_BATCH.name else 1 for c in configs)
    runtime = context.runtime
    with runtime.sessions() as session:
        # Lock our row first: if another worker took the lease meanwhile, create nothing.
        held = session.execute(
            update(Job)
            .where(Job.id == context.job_id, Job.lease_owner == runtime.owner)
            .values(progress=0.0)
            .execution_options(synchronize_session=False)
        ).rowcount
        existing = session.scalar(select(func.count()).where(Job.parent_id == context.job_id))
        if held != 1 or existing:
            session.rollback()
            raise JobStoppedError("lease lost")
        children = [
            Job(
                kind=kind,
                config=config,
                parent_id=context.job_id,
                submitter_id=context.submitter_id,
                max_attempts=context.max_attempts,
            )
            for config in configs
        ]
        session.add_all(children)
        session.commit()
        ids = [child.id for child in children]
    for child_id in ids:
        enqueue_job(runtime.celery, child_id, kind)
    return JobOutcome(wait_for_children=True, values={"result": {"runs": n_runs}})


def _record(result: dict[str, Any]) -> RunRecord:
    """The learner's run record inside a child job's result (a run's entry of it)."""
    return RunRecord.from_dict({k: v for k, v in result.items() if k in RECORD_FIELDS})


def _failure(child: Job, spec: dict[str, Any]) -> RunFailure:
    """A run of ``child`` that has no record: the child job did not succeed."""
    return RunFailure(
        spec=spec,
        label=RunSpec.from_dict(spec).label,
        error_type=f"job {child.status}",
        message=child.error or child.status,
        traceback=child.traceback or "",
    )


def child_outcomes(child: Job) -> tuple[list[RunRecord], list[RunFailure]]:
    """The records of a final child job's runs and the failures of the others: a
    ``reproduce_run`` job's one run; each run of a ``reproduce_batch`` job (its own failure
    if the batch recorded one, else the job's status and error)."""
    if child.kind == REPRODUCE_RUN.name:
        spec = {k: v for k, v in child.config.items() if k != "checkpoint_every"}
        if child.status == "succeeded" and child.result:
            return [_record(child.result)], []
        return [], [_failure(child, spec)]
    result = child.result or {}
    records = [_record(entry) for entry in result.get("runs", [])]
    recorded = [RunFailure.from_dict(failure) for failure in result.get("failed", [])]
    by_key = {RunSpec.from_dict(failure.spec).key: failure for failure in recorded}
    done = {record.run_spec.key for record in records}
    failures = []
    for spec in child.config.get("runs", []):
        key = RunSpec.from_dict(spec).key
        if key not in done:
            failures.append(by_key.get(key) or _failure(child, spec))
    return records, failures


def _aggregate(context: JobContext, children: list[Job]) -> JobOutcome:
    runs: list[RunRecord] = []
    failures: list[RunFailure] = []
    for child in children:
        records, failed = child_outcomes(child)
        runs += records
        failures += failed
    artifacts: dict[str, str] = {}
    claims: list[dict[str, Any]] = []
    if runs:
        with tempfile.TemporaryDirectory(prefix="bgrl-reproduce-") as tmp:
            out = Path(tmp)
            save_results(out / "results.json", Results(config={}, runs=runs))
            write_reproduction(  # every run is in results.json: this only writes the outputs
                out,
                [run.run_spec for run in runs],
                workers=1,
                config_note={"job": {"id": context.job_id, "options": context.config}},
            )
            results = load_results(out / "results.json")
            results.failed = failures
            save_results(out / "results.json", results)
            claims = json.loads((out / "summary.json").read_text()).get("claims", [])
            for path in sorted(out.iterdir()):
                kind = "plot" if path.suffix in PLOT_SUFFIXES else "results"
                artifacts[path.name] = context.store_file(path, kind=kind, name=path.name)
    result = {
        "runs": len(runs) + len(failures),
        "succeeded": len(runs),
        "failed": [
            {"label": f.label, "status": f.error_type, "error": f.message} for f in failures
        ],
        "artifacts": artifacts,
        "claims": claims,
    }
    error = None
    if failures:
        names = "; ".join(str(f) for f in failures)
        error = f"{len(failures)} of {len(runs) + len(failures)} runs did not succeed: {names}"
    return JobOutcome(result=result, error=error)
