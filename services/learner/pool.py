"""Running many specs over spawned worker processes, with resume and failure isolation.

:func:`reproduce` runs the specs of a reproduction that ``out_dir/results.json`` does not
hold yet, rewrites that file after every finished run (an interrupted reproduction resumes
where it stopped), then writes the CSV, the summary and the plots. A run that raises is
recorded in ``results.json["failed"]`` with its error type, message and traceback while the
other runs go on; a later call retries it. :func:`hf_policy_sweep` does the same for stage 2
alone (``hf_policies.json``).
"""

from __future__ import annotations

import functools
import hashlib
import json
import multiprocessing
import signal
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple, Protocol, TypeVar

from services.core.files import write_json_atomic
from services.core.lifetime import die_with_parent
from services.learner.feedback import FeedbackConfig
from services.learner.feedback_sources import (
    FEEDBACK_SOURCE,
    FeedbackSourceFactory,
    one_feedback_source,
)
from services.learner.hf_methods import PAPER_METHOD
from services.learner.outputs import Results, load_results, save_results, write_outputs
from services.learner.ppo import PPOConfig, lockstep_key
from services.learner.runs import (
    SPL_TARGET,
    HFPolicySpec,
    RunFailure,
    RunRecord,
    hf_policy_run,
    hf_policy_runs,
    run_lockstep,
    run_one,
)
from services.learner.specs import ACCURACIES, N_VSSG_EVAL_STARTS, RunSpec, settings_conflict


class _Spec(Protocol):
    @property
    def key(self) -> tuple[Any, ...]: ...

    @property
    def label(self) -> str: ...

    def to_dict(self) -> dict[str, Any]: ...


SpecT = TypeVar("SpecT", bound=_Spec)
ResultT = TypeVar("ResultT")


def _worker_init() -> None:
    # a run pool's process ends with its parent, even a parent killed with SIGKILL (a job
    # worker restarted by `bgrl up`): no orphan keeps computing
    parent = multiprocessing.parent_process()
    if parent is not None and parent.pid is not None:
        die_with_parent(parent.pid)
    import torch

    torch.set_num_threads(1)  # one run per core
    # Ctrl-C reaches the whole process group: the parent alone handles it (run_isolated
    # stops the workers), so a run is never recorded as failed with a KeyboardInterrupt.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _guarded(function: Callable[[SpecT], ResultT], spec: SpecT) -> ResultT | RunFailure:
    """Run ``function(spec)`` in a worker; an exception becomes a :class:`RunFailure`."""
    try:
        return function(spec)
    except Exception as exc:  # every run error is recorded, none is lost
        return RunFailure.from_exception(spec, exc)


def run_isolated(
    function: Callable[[SpecT], ResultT],
    specs: Sequence[SpecT],
    *,
    workers: int,
    on_result: Callable[[ResultT], None],
    on_failure: Callable[[RunFailure], None],
) -> None:
    """Run ``function`` on every spec over ``workers`` spawned processes.

    Each finished run calls ``on_result`` (in completion order) or, if it raised or its
    worker died, ``on_failure``: one run's failure never stops or loses the others.

    If the caller is interrupted (Ctrl-C) or a callback raises, the runs not started are
    dropped and the workers are stopped at once before the exception goes on: what
    finished has been handed over, the rest is for a rerun.
    """
    if not specs:
        return
    context = multiprocessing.get_context("spawn")
    pool = ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init)
    try:
        futures: dict[Future[Any], SpecT] = {
            pool.submit(_guarded, function, spec): spec for spec in specs
        }
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except Exception as exc:  # e.g. a worker killed (BrokenProcessPool)
                outcome = RunFailure.from_exception(futures[future], exc)
            if isinstance(outcome, RunFailure):
                on_failure(outcome)
            else:
                on_result(outcome)
    except BaseException:
        _stop(pool)
        raise
    pool.shutdown(wait=True)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Drop the pool's queued work and end its workers now (shutdown alone would wait for
    every queued run)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    manager = getattr(pool, "_executor_manager_thread", None)
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    # The pool's manager thread reaps the workers it sees die: let it finish before joining
    # them here, as two threads reaping one child can leave it listed as alive for good.
    if manager is not None:
        manager.join(timeout=10)
    for process in processes:
        process.join(timeout=10)


def _refuse_the_others_folder(out: Path, record: str, study: str) -> None:
    """A reproduction and a stage-2 sweep each need a folder of their own (both write
    summary.md): a one-line ValueError if ``out`` holds the other's ``record``."""
    if (out / record).exists():
        raise ValueError(
            f"{out} holds {study}: its {record} and summary.md are kept; "
            "give this one a folder of its own"
        )


def _each_run_once(specs: Sequence[_Spec]) -> None:
    """A one-line ValueError naming the first run ``specs`` hold twice (it would be trained,
    and counted as a seed, twice)."""
    seen: set[tuple[Any, ...]] = set()
    for spec in specs:
        if spec.key in seen:
            raise ValueError(f"{spec.label} given twice: give each run once")
        seen.add(spec.key)


def validate_maps(specs: Sequence[RunSpec]) -> None:
    """Load every map the specs name and check that its goal can be reached; a one-line
    ValueError for the first bad one."""
    from services.sim.maps import MapError, load_map
    from services.sim.oracle import Oracle

    for map_path in sorted({s.map_path for s in specs if s.map_path is not None}):
        try:
            Oracle.for_map(load_map(map_path)).check_reachable(f"map file {map_path}")
        except MapError as exc:
            raise ValueError(str(exc).splitlines()[0]) from None


CHECKPOINT_FOLDER = "checkpoints"
"""Sub-folder of a reproduction where its runs keep their checkpoints (one file per run,
the same in a lockstep batch and alone: :func:`checkpoint_path`)."""
LOCKSTEP_MAX_RUNS = 32
"""Most runs of one lockstep batch. Its headless envs share one pybullet world
(:mod:`services.sim.world`), so an env no longer costs ~30 MB a run; the cap keeps a
batch, which one worker holds and which ends (or is lost) as a whole, a part of a sweep."""


@dataclass(frozen=True)
class RunBatch:
    """Runs trained together in lockstep in one worker (:func:`run_lockstep`), each
    checkpointed in ``checkpoint_dir`` if given (:func:`checkpoint_path`)."""

    specs: tuple[RunSpec, ...]
    checkpoint_dir: str | None = None

    @property
    def key(self) -> tuple[Any, ...]:
        """The runs' keys."""
        return tuple(s.key for s in self.specs)

    @property
    def label(self) -> str:
        """E.g. ``lockstep batch of 50 runs (sssg rl_sparse seed=0, ...)``."""
        return f"lockstep batch of {len(self.specs)} runs ({self.specs[0].label}, ...)"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: the runs' specs and the checkpoint folder."""
        return {"runs": [s.to_dict() for s in self.specs], "checkpoint_dir": self.checkpoint_dir}

    def failures(self, failure: RunFailure) -> list[RunFailure]:
        """The batch's failure (e.g. its worker died) as one failure per run."""
        return [replace(failure, spec=s.to_dict(), label=s.label) for s in self.specs]


CHECKPOINT_EVERY = 10
"""Updates between two checkpoints of a run of a sweep (1280 env steps by default)."""


def checkpoint_path(folder: str | Path, spec: RunSpec) -> Path:
    """Where a sweep keeps the checkpoint of the run of ``spec`` until its record is saved,
    in a lockstep batch or alone (either resumes from the other's): ``folder/<digest of the
    spec>.pt``."""
    digest = hashlib.sha256(json.dumps(spec.to_dict(), sort_keys=True).encode()).hexdigest()
    return Path(folder) / f"{digest[:20]}.pt"


def lockstep_batches(
    specs: Sequence[RunSpec],
    workers: int,
    max_runs: int = LOCKSTEP_MAX_RUNS,
    checkpoint_dir: str | Path | None = None,
) -> list[RunBatch]:
    """Split ``specs`` into lockstep batches: runs of one PPO shape
    (:func:`~services.learner.ppo.lockstep_key`) together, each group dealt round-robin into
    at least ``workers`` batches (all workers busy) of at most ``max_runs``."""
    groups: dict[str, list[RunSpec]] = {}
    for spec in specs:
        groups.setdefault(lockstep_key(spec.ppo_config()), []).append(spec)
    batches = []
    for group in groups.values():
        n_batches = min(len(group), max(workers, -(-len(group) // max_runs)))
        batches += [
            RunBatch(
                tuple(group[b::n_batches]),
                None if checkpoint_dir is None else str(checkpoint_dir),
            )
            for b in range(n_batches)
        ]
    return batches


def _run_batch(
    batch: RunBatch, feedback_factory: FeedbackSourceFactory | None = None
) -> list[RunRecord | RunFailure]:
    folder = batch.checkpoint_dir
    return run_lockstep(
        batch.specs,
        checkpoint_paths=None
        if folder is None
        else [checkpoint_path(folder, s) for s in batch.specs],
        checkpoint_every=CHECKPOINT_EVERY,
        feedback_factory=feedback_factory,
    )


def _run_alone(
    spec: RunSpec,
    checkpoint_dir: str | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> RunRecord:
    """:func:`run_one`, checkpointed at :func:`checkpoint_path` in ``checkpoint_dir`` if
    given (as in a lockstep batch)."""
    return run_one(
        spec,
        checkpoint_path=None if checkpoint_dir is None else checkpoint_path(checkpoint_dir, spec),
        checkpoint_every=CHECKPOINT_EVERY,
        feedback_factory=feedback_factory,
    )


def run_sweep(
    specs: Sequence[RunSpec],
    *,
    workers: int,
    lockstep: bool,
    on_result: Callable[[RunRecord], None],
    on_failure: Callable[[RunFailure], None],
    checkpoint_dir: str | Path | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> None:
    """Every run of ``specs`` over ``workers`` processes: each alone (:func:`run_one`), or
    in lockstep batches (:func:`lockstep_batches`, :func:`run_lockstep`; bit-identical
    records). Each run's record or failure is handed over as it is known (a batch's when
    the batch ends). With ``checkpoint_dir``, every run writes its checkpoint there
    (:func:`checkpoint_path`, one file per run whichever the path) and resumes from it, so
    a sweep interrupted or killed resumes every run, in lockstep or alone; a run's
    checkpoint is deleted once its record was handed over.
    ``feedback_factory`` makes the labels of runs with ``virtual_subject`` feedback."""
    if not specs:
        return
    if checkpoint_dir is not None:
        Path(checkpoint_dir).mkdir(parents=True, exist_ok=True)

    def done(record: RunRecord) -> None:
        on_result(record)
        if checkpoint_dir is not None:
            checkpoint_path(checkpoint_dir, record.run_spec).unlink(missing_ok=True)

    def batch_done(outcomes: list[RunRecord | RunFailure]) -> None:
        for outcome in outcomes:
            if isinstance(outcome, RunFailure):
                on_failure(outcome)
            else:
                done(outcome)

    def batch_failed(failure: RunFailure) -> None:
        batch = RunBatch(tuple(RunSpec.from_dict(s) for s in failure.spec["runs"]))
        for run_failure in batch.failures(failure):
            on_failure(run_failure)

    if lockstep:
        batches = lockstep_batches(specs, workers, checkpoint_dir=checkpoint_dir)
        run_batch = functools.partial(_run_batch, feedback_factory=feedback_factory)
        run_isolated(
            run_batch, batches, workers=workers, on_result=batch_done, on_failure=batch_failed
        )
    else:
        run = functools.partial(
            _run_alone,
            checkpoint_dir=None if checkpoint_dir is None else str(checkpoint_dir),
            feedback_factory=feedback_factory,
        )
        run_isolated(run, specs, workers=workers, on_result=done, on_failure=on_failure)
    if checkpoint_dir is not None and not any(Path(checkpoint_dir).iterdir()):
        Path(checkpoint_dir).rmdir()  # every run done: no folder left behind


def reproduce(
    out_dir: str | Path,
    specs: Sequence[RunSpec],
    *,
    workers: int = 2,
    lockstep: bool = True,
    config_note: dict[str, Any] | None = None,
    on_done: Callable[[RunRecord], None] | None = None,
    on_failure: Callable[[RunFailure], None] | None = None,
    on_resume: Callable[[int], None] | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> Results:
    """Run every spec not yet in ``out_dir/results.json`` and write the outputs.

    With ``lockstep`` (the default) the runs train in lockstep batches, one per worker
    (:func:`run_sweep`); False runs each alone (the same records). Either way each run is
    checkpointed in ``out_dir/checkpoints`` (a reproduction interrupted mid-run resumes
    every run from its last checkpoint, in lockstep or alone).
    ``feedback_factory`` makes the labels of specs with ``virtual_subject`` feedback
    (``services.worker.e2e_feedback.VirtualSubjectFactory``).

    ``on_done`` is called with each new run's record, ``on_failure`` with each failed run,
    ``on_resume`` once with the number of specs skipped because they are already done
    (progress bars start there).

    ``out_dir`` accumulates: runs from earlier calls stay in ``results.json`` and in the
    summary and plots, so a reproduction can be extended by more seeds or methods; failed
    runs of earlier calls are retried. Runs with other settings (labels, stage-2 method, map,
    PPO overrides), maps that do not load and a run ``specs`` hold twice are refused with a
    ValueError before anything runs. Returns the results; ``results.failed`` lists the runs
    that failed in this call (and earlier failures of runs this call did not include).
    """
    _each_run_once(specs)
    validate_maps(specs)
    out = Path(out_dir)
    _refuse_the_others_folder(out, "hf_policies.json", "a stage-2 sweep (bgrl hf-sweep)")
    results_path = out / "results.json"
    config = {
        "ppo": asdict(PPOConfig()),
        "feedback": asdict(FeedbackConfig()),
        "n_vssg_eval_starts": N_VSSG_EVAL_STARTS,
        "spl_target": SPL_TARGET,
        "label_steps_counted_in_budget": False,
        **(config_note or {}),
    }
    earlier = load_results(results_path) if results_path.exists() else Results(config=config)
    runs = earlier.runs
    if settings_conflict([*specs, *(r.run_spec for r in runs)]):
        raise ValueError(
            f"{out} holds runs with other settings (labels, stage-2 method, map or PPO "
            "overrides); use another output folder"
        )
    source = one_feedback_source(
        out,
        earlier.config.get(FEEDBACK_SOURCE),
        (r.feedback for r in runs),
        (s.feedback for s in specs),
        feedback_factory,
    )
    if source is not None:
        config[FEEDBACK_SOURCE] = source
    out.mkdir(parents=True, exist_ok=True)
    done = {r.run_spec.key for r in runs}
    pending = [s for s in specs if s.key not in done]
    if on_resume is not None:
        on_resume(len(specs) - len(pending))
    attempted = {s.key for s in specs} | done
    not_retried = [f for f in earlier.failed if RunSpec.from_dict(f.spec).key not in attempted]
    results = Results(config=config, runs=runs, failed=not_retried)

    def finished(record: RunRecord) -> None:
        results.runs.append(record)
        save_results(results_path, results)
        if on_done is not None:
            on_done(record)

    def failed(failure: RunFailure) -> None:
        results.failed.append(failure)
        save_results(results_path, results)
        if on_failure is not None:
            on_failure(failure)

    try:
        run_sweep(
            pending, workers=workers, lockstep=lockstep, on_result=finished,
            on_failure=failed, checkpoint_dir=out / CHECKPOINT_FOLDER,
            feedback_factory=feedback_factory,
        )  # fmt: skip
    except KeyboardInterrupt:  # the CSV, summary and plots cover the runs kept so far
        if results.runs:
            write_outputs(out, results.runs)
        raise
    save_results(results_path, results)
    write_outputs(out, results.runs)
    return results


def hf_policy_sweep(
    out_dir: str | Path,
    *,
    tasks: Sequence[str] = ("sssg", "vssg"),
    accuracies: Sequence[float] = ACCURACIES,
    seeds: int = 10,
    labels: Sequence[int] = (1000,),
    methods: Sequence[str] = (PAPER_METHOD,),
    workers: int = 1,
    on_failure: Callable[[RunFailure], None] | None = None,
    feedback: str = "oracle",
    label_channel: str = "hard",
    feedback_factory: FeedbackSourceFactory | None = None,
    lockstep: bool = True,
) -> tuple[list[dict[str, Any]], list[RunFailure]]:
    """:func:`~services.learner.runs.hf_policy_run` over tasks x C x labels x methods x seeds.

    With ``lockstep`` (the default) the runs are dealt into batches, one or more per worker,
    whose sessions of one batched stage-2 method learn together
    (:func:`~services.learner.runs.hf_policy_runs`; the same rows bit for bit, but for
    ``wall_seconds``); without, each runs alone.

    With ``virtual_subject`` feedback the ``accuracies`` are the target accuracies of the
    subject's decoder (``feedback_factory`` makes the labels), read through
    ``label_channel``.

    Writes ``out_dir/hf_policies.json`` (``{"config": {...}, "runs": [...], "failed":
    [...]}``) after every run; runs already there are skipped, failed ones retried (earlier
    failures of runs this call does not include are kept). ``config`` records the virtual
    subjects' settings (``feedback_source``: ``feedback_factory.describe()``); a folder holds
    one set. A file there that is not such a document, virtual-subject rows made with other
    settings, or a run named twice (a task, C, label budget or method repeated), is a
    ValueError naming it, before anything runs. Returns (rows, failures), the failures of
    this call and the earlier ones kept.
    """
    virtual = feedback == "virtual_subject"
    specs = [
        HFPolicySpec(
            task,
            None if virtual else accuracy,
            seed,
            n_labels,
            method,
            feedback,
            label_channel,
            accuracy if virtual else None,
        )
        for seed in range(seeds)
        for method in methods
        for n_labels in labels
        for task in tasks
        for accuracy in accuracies
    ]
    _each_run_once(specs)
    out = Path(out_dir)
    _refuse_the_others_folder(out, "results.json", "a reproduction (bgrl reproduce)")
    path = out / "hf_policies.json"
    rows, earlier_failures, recorded = load_sweep(path) if path.exists() else ([], [], None)
    source = one_feedback_source(
        out,
        recorded,
        (row.get("feedback", "oracle") for row in rows),
        (s.feedback for s in specs),
        feedback_factory,
    )
    config = {} if source is None else {FEEDBACK_SOURCE: source}
    out.mkdir(parents=True, exist_ok=True)
    done = {sweep_row_key(r) for r in rows}
    attempted = {s.key for s in specs}
    failures: list[RunFailure] = []
    kept_failures = [f for f in earlier_failures if _sweep_spec_key(f.spec) not in attempted]

    def save() -> None:
        failed = [f.to_dict() for f in [*kept_failures, *failures]]
        document = {"config": config, "runs": rows, "failed": failed}
        write_json_atomic(path, document, indent=None)

    def finished(row: dict[str, Any]) -> None:
        rows.append(row)
        save()

    def failed(failure: RunFailure) -> None:
        failures.append(failure)
        save()
        if on_failure is not None:
            on_failure(failure)

    pending = [s for s in specs if s.key not in done]
    if not lockstep:
        run = functools.partial(hf_policy_run, feedback_factory=feedback_factory)
        run_isolated(run, pending, workers=workers, on_result=finished, on_failure=failed)
        save()
        return rows, [*kept_failures, *failures]

    def batch_done(outcomes: list[dict[str, Any] | RunFailure]) -> None:
        for outcome in outcomes:
            if isinstance(outcome, RunFailure):
                failed(outcome)
            else:
                finished(outcome)

    def batch_failed(failure: RunFailure) -> None:  # the worker died: every run of it
        for spec in failure.spec["runs"]:
            failed(replace(failure, spec=spec, label=HFPolicySpec(**spec).label))

    n_batches = min(len(pending), max(workers, -(-len(pending) // LOCKSTEP_MAX_RUNS)))
    batches = [HFPolicyBatch(tuple(pending[b::n_batches])) for b in range(n_batches)]
    run_batch = functools.partial(_run_hf_batch, feedback_factory=feedback_factory)
    run_isolated(run_batch, batches, workers=workers, on_result=batch_done, on_failure=batch_failed)
    save()
    return rows, [*kept_failures, *failures]


@dataclass(frozen=True)
class HFPolicyBatch:
    """Stage-2-alone runs learning together in one worker (:func:`hf_policy_runs`)."""

    specs: tuple[HFPolicySpec, ...]

    @property
    def label(self) -> str:
        """E.g. ``lockstep batch of 30 runs (vssg C=0.7 seed=3 labels=1000 paper, ...)``."""
        return f"lockstep batch of {len(self.specs)} runs ({self.specs[0].label}, ...)"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form: the runs' specs."""
        return {"runs": [s.to_dict() for s in self.specs]}


def _run_hf_batch(
    batch: HFPolicyBatch, feedback_factory: FeedbackSourceFactory | None = None
) -> list[dict[str, Any] | RunFailure]:
    return hf_policy_runs(batch.specs, feedback_factory)


def sweep_row_key(row: dict[str, Any]) -> tuple[Any, ...]:
    """The ``HFPolicySpec.key`` of a ``hf_policies.json`` row."""
    method = row.get("method", PAPER_METHOD)
    key = (row["task"], row["accuracy"], row["seed"], row["n_labels"], method)
    feedback = row.get("feedback", "oracle")  # absent in sweeps made before other feedback
    if feedback == "oracle":
        return key
    return (*key, feedback, row["label_channel"], row["decoder_accuracy_target"])


def _sweep_spec_key(spec: dict[str, Any]) -> tuple[Any, ...]:
    return HFPolicySpec(**spec).key


class SweepFile(NamedTuple):
    """What a ``hf_policies.json`` holds."""

    rows: list[dict[str, Any]]
    failures: list[RunFailure]
    feedback_source: dict[str, Any] | None
    """The virtual subjects' settings (``FeedbackSourceFactory.describe()``); None in a file
    of the oracle's rows alone or written before the record (then the default settings)."""


def load_sweep(path: str | Path) -> SweepFile:
    """The rows, failures and feedback-source settings of a ``hf_policies.json``; a one-line
    ValueError naming the file if it is not one (the file is left as it is)."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
        rows = document["runs"]
        failures = [RunFailure.from_dict(f) for f in document.get("failed", [])]
        source = document.get("config", {}).get(FEEDBACK_SOURCE)
        if not isinstance(rows, list):
            raise TypeError("runs is not a list")
        if not isinstance(source, dict | None):
            raise TypeError(f"config.{FEEDBACK_SOURCE} is not an object")
        for row in rows:
            sweep_row_key(row)
            for name in ("greedy_spl", "sampled_success_rate"):  # what the report reads
                if not isinstance(row[name], int | float):
                    raise TypeError(f"{name} is not a number")
        for failure in failures:
            _sweep_spec_key(failure.spec)
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read it ({exc})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a `bgrl hf-sweep` results file ({exc!r})") from None
    return SweepFile(rows, failures, source)
