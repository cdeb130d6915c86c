"""``reproduce_batch`` jobs: runs of a reproduction trained together in lockstep in one worker
(:func:`services.learner.runs.run_lockstep`: stage 2 of the hf_sparse runs, then PPO, each
run's record the one it gets alone, ``wall_seconds`` aside).

Per run, the job's checkpoint folder (``checkpoint/job-<id>/`` in the artifact store) holds
its learner checkpoint ``<digest>.pt`` (:func:`services.learner.pool.checkpoint_path`),
rewritten every ``checkpoint_every`` updates, and once the run is done ``<digest>.json``,
its entry of the job's result (its record and the ids of its stored policies), when its
checkpoint is deleted. A job claimed again (its worker was killed, or a retry after a run
of it failed) resumes every unfinished run from its checkpoint and keeps the finished
ones. Stage 2 is not checkpointed: a resumed batch learns pi_HF again (the same pi_HF).

The job's result: ``runs`` (per finished run, what a ``reproduce_run`` job's result holds,
plus ``model_artifact_ids``, its best policy's files) and ``failed`` (the learner's run
failures); a failed run fails the job, naming it. Progress: ``steps_done`` is the sum over
the runs, ``progress`` its share of all the runs' steps. Cancel is checked after every label
of stage 2 and every env step of PPO. TensorBoard: each run's metrics and SPL under
``tensorboard/job-<id>/<digest>/``.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from torch.utils.tensorboard import SummaryWriter

from services.core.artifacts import TENSORBOARD_KIND
from services.learner.pool import checkpoint_path
from services.learner.ppo import Callback
from services.learner.runs import RunFailure, RunRecord, run_lockstep
from services.learner.specs import RunSpec
from services.worker.runtime import JobConfigError, JobContext, JobOutcome
from services.worker.training import (
    PROGRESS_EVERY_S,
    SPL_TAG,
    TENSORBOARD_FLUSH_S,
    checkpoint_progress,
    store_trained_policies,
    warm_oracle,
)


class BatchProgress:
    """The batch's steps (per run) written to the job row at most every
    :data:`~services.worker.training.PROGRESS_EVERY_S`."""

    def __init__(self, context: JobContext, steps: list[int], totals: list[int]) -> None:
        self.context = context
        self.steps = steps
        self.totals = totals
        self.last_write = 0.0

    def advance(self, row: int, global_step: int) -> None:
        """Run ``row`` is at ``global_step``."""
        self.steps[row] = global_step
        now = time.monotonic()
        if now - self.last_write >= PROGRESS_EVERY_S:
            self.last_write = now
            done = sum(self.steps)
            self.context.update(steps_done=done, progress=min(done / sum(self.totals), 0.99))


class BatchRunProgress(Callback):
    """One run's hooks: cancel (or a lost lease) raises :class:`JobStoppedError` at its next
    step (the run leaves the batch; all runs see it at the same step), its steps go to the
    batch's progress, its metrics and SPL to its TensorBoard ``writer``."""

    def __init__(self, progress: BatchProgress, row: int, writer: SummaryWriter) -> None:
        self.progress = progress
        self.row = row
        self.writer = writer

    def on_step(self, global_step: int, info: dict[str, Any]) -> bool:
        self.progress.context.check_stop()
        return True

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        for name, value in metrics.items():
            self.writer.add_scalar(name, value, global_step)
        self.progress.advance(self.row, global_step)
        return True

    def on_eval(self, global_step: int, spl: float) -> bool:
        self.writer.add_scalar(SPL_TAG, spl, global_step)
        self.writer.flush()
        self.progress.advance(self.row, global_step)
        return True


def batch_specs(config: dict[str, Any]) -> tuple[list[RunSpec], int | None]:
    """The run specs and ``checkpoint_every`` of a ``reproduce_batch`` job config."""
    given = dict(config)
    every = given.pop("checkpoint_every", None)
    runs = given.pop("runs", None)
    if given or not isinstance(runs, list) or not runs:
        raise JobConfigError("a reproduce batch's config is {runs: [run specs], checkpoint_every}")
    try:
        return [RunSpec.from_dict(run) for run in runs], None if every is None else int(every)
    except (TypeError, ValueError) as exc:
        raise JobConfigError(f"not a run spec: {exc}") from None


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` to ``path`` atomically (a temp file beside it, then rename)."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as handle:
        json.dump(data, handle)
    os.replace(tmp, path)


def reproduce_batch(context: JobContext) -> JobOutcome:
    """Handler of ``reproduce_batch`` jobs (see the module doc)."""
    specs, every = batch_specs(context.config)
    every = every or context.runtime.settings.checkpoint_every
    folder = context.job_dir("checkpoint")
    checkpoints = [checkpoint_path(folder, spec) for spec in specs]
    done_files = [path.with_suffix(".json") for path in checkpoints]
    finished = {
        i: json.loads(path.read_text()) for i, path in enumerate(done_files) if path.exists()
    }
    totals = [spec.ppo_config().total_steps for spec in specs]
    pending = [i for i in range(len(specs)) if i not in finished]
    failures: list[RunFailure] = []
    if pending:
        for spec in {spec.map_path: spec for spec in specs}.values():  # one per map
            warm_oracle(spec, context.runtime.settings.data_dir)
        steps = [
            totals[i] if i in finished
            else checkpoint_progress(checkpoints[i])[0] if checkpoints[i].exists()
            else 0
            for i in range(len(specs))
        ]  # fmt: skip
        if any(checkpoints[i].exists() for i in pending) or finished:
            context.update(resumed_from_step=sum(steps), steps_done=sum(steps))
        context.check_stop()
        progress = BatchProgress(context, [steps[i] for i in pending], [totals[i] for i in pending])
        board = context.job_dir(TENSORBOARD_KIND)
        with ExitStack() as stack:
            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bgrl-batch-")))
            callbacks = []
            for row, i in enumerate(pending):
                writer = SummaryWriter(
                    str(board / checkpoints[i].stem), flush_secs=TENSORBOARD_FLUSH_S
                )
                stack.enter_context(writer)
                callbacks.append(BatchRunProgress(progress, row, writer))
                (work / checkpoints[i].stem).mkdir()
            outcomes = run_lockstep(
                [specs[i] for i in pending],
                callbacks=callbacks,
                checkpoint_paths=[checkpoints[i] for i in pending],
                checkpoint_every=every,
                on_label=lambda _record: context.check_stop(),  # cancel during stage 2 too
                model_paths=[work / checkpoints[i].stem / "policy.pt" for i in pending],
                last_model_paths=[work / checkpoints[i].stem / "policy_last.pt" for i in pending],
                portable=True,
            )
            for i, outcome in zip(pending, outcomes, strict=True):
                if isinstance(outcome, RunFailure):
                    failures.append(outcome)
                    continue
                finished[i] = _stored_run(context, outcome, work / checkpoints[i].stem)
                _write_json(done_files[i], finished[i])
                checkpoints[i].unlink(missing_ok=True)
        context.check_stop()
    result = {
        "runs": [finished[i] for i in sorted(finished)],
        "failed": [failure.to_dict() for failure in failures],
    }
    error = None
    if failures:
        names = "; ".join(str(failure) for failure in failures)
        error = f"{len(failures)} of {len(specs)} runs failed: {names}"
    steps_done = sum(totals[i] for i in finished)
    return JobOutcome(result=result, error=error, values={"steps_done": steps_done})


def _stored_run(context: JobContext, record: RunRecord, work: Path) -> dict[str, Any]:
    """A finished run's entry of the result: its record and its stored policies."""
    stored, best_ids = store_trained_policies(context, work / "policy.pt", work / "policy_last.pt")
    return {**record.to_dict(), **stored, "model_artifact_ids": best_ids}
