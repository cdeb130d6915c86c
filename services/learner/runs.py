"""Executing one run: :func:`run_one` (spec -> :class:`RunRecord`) and :func:`hf_policy_run`.

Both are pure functions of their arguments (seeded through :mod:`services.learner.seeding`),
close every env they open on every path, and return JSON-able frozen records whose
``to_dict()`` field names are those of ``results.json`` / ``hf_policies.json``.

The 1000 label-collection steps of stage 2 are *not* counted in the RL budget, as in the
paper, where pi_HF is learned in a separate session before RL.
"""

from __future__ import annotations

import importlib.metadata
import platform
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack, closing
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from services.learner.evaluation import eval_seeds, evaluate_spl, run_episode
from services.learner.feedback import (
    FeedbackCollection,
    FeedbackConfig,
    FeedbackLearner,
    HFPolicy,
    HFResult,
    default_max_steps,
)
from services.learner.feedback_buffer import FeedbackRecord
from services.learner.feedback_lockstep import collect_feedback_lockstep, lockstep_feedback_key
from services.learner.feedback_sources import (
    DecodedFeedbackSource,
    FeedbackSourceFactory,
    OracleFeedbackSource,
)
from services.learner.hf_methods import PAPER_METHOD, get_method
from services.learner.policy_files import write_beside_torchscript
from services.learner.ppo import Callback, TrainResult, check_one_shape, train, train_lockstep
from services.learner.seeding import RunSeeds, Stream, evaluation_reset_seeds
from services.learner.specs import (
    N_VSSG_EVAL_STARTS,
    TASK_ENV_IDS,
    RunSpec,
    check_decoder_accuracy,
    check_feedback,
)

SPL_TARGET = 0.7
N_HF_PROBE_EPISODES = 20
"""Episodes of the *sampling* pi_HF that :func:`hf_policy_run` measures."""


@dataclass(frozen=True)
class RunRecord:
    """Outcome of one run (one ``runs`` entry of ``results.json``)."""

    task: str
    method: str
    accuracy: float | None
    seed: int
    hf_treatment: str | None
    curve: list[list[float]]
    """``[[env_steps, SPL of the greedy pi_RL], ...]`` at every evaluation."""
    final_spl: float
    hf_policy_spl: float | None
    """SPL of the greedy pi_HF on the evaluation starts (hf_sparse), measured before RL."""
    wall_seconds: float
    steps_to_0_7: int | None
    n_episodes: int = 0
    n_hf_episodes: int = 0
    training_episodes: list[dict[str, Any]] | None = None
    """Per ``eval_every`` window: episodes, HF episodes, mean length, success, collision."""
    hf: dict[str, Any] | None = None
    """Stage 2's summary (Fhat's validation accuracies, realised label accuracy)."""
    spec: dict[str, Any] | None = None
    """The :class:`RunSpec` as a dict."""
    best_step: int | None = None
    """Env step of the best evaluation (the first of equal bests), whose weights a run
    keeps beside the last (None in records written before it was kept)."""
    best_spl: float | None = None
    """SPL of that evaluation."""
    n_labels: int = 0
    """Labels pi_HF was learned from (0 for a run without stage 2)."""
    feedback: str | None = None
    """``oracle`` or ``virtual_subject`` (hf_sparse; None otherwise)."""
    label_channel: str | None = None
    """``hard`` or ``soft`` (hf_sparse; None otherwise)."""
    decoder_accuracy: float | None = None
    """Held-out hard accuracy of the virtual subject's decoder (None for the oracle)."""
    subject_quality: float | None = None
    """The virtual subject's quality knob that gave it (None for the oracle)."""
    environment: dict[str, str] | None = None
    """Python's and the numeric packages' versions and the machine architecture the run had
    (:func:`software_environment`): a run is bit-for-bit repeatable with the same ones only
    (None in records written before it was kept)."""

    @property
    def run_spec(self) -> RunSpec:
        """The spec this record came from."""
        if self.spec is None:
            raise ValueError("this record carries no spec")
        return RunSpec.from_dict(self.spec)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunRecord:
        """Rebuild from :meth:`to_dict` output (extra keys are refused)."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown run record fields {sorted(unknown)}")
        if "feedback" not in data and data.get("spec") is not None:
            # written before the record format named the feedback: the spec says it
            spec = RunSpec.from_dict(data["spec"])
            data = {**feedback_fields(spec.method == "hf_sparse", spec, None), **data}
        return cls(**data)


@dataclass(frozen=True)
class RunFailure:
    """A run that raised: its spec and the error (type, message, traceback)."""

    spec: dict[str, Any]
    label: str
    """The run's short name (``RunSpec.label``)."""
    error_type: str
    message: str
    traceback: str

    @classmethod
    def from_exception(cls, spec: RunSpec | HFPolicySpec, exc: BaseException) -> RunFailure:
        """Record ``exc`` raised by the run of ``spec``."""
        return cls(
            spec=spec.to_dict(),
            label=spec.label,
            error_type=type(exc).__name__,
            message=str(exc),
            traceback="".join(traceback.format_exception(exc)),
        )

    def __str__(self) -> str:
        return f"{self.label}: {self.error_type}: {self.message}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunFailure:
        """Rebuild from :meth:`to_dict` output."""
        return cls(**data)


def steps_to_reach(curve: Sequence[Sequence[float]], target: float = SPL_TARGET) -> int | None:
    """First evaluated env step with SPL >= target, or None if never reached."""
    return next((int(step) for step, spl in curve if spl >= target), None)


def episode_stats(
    episodes: Sequence[Sequence[Any]], window: int, total_steps: int
) -> list[dict[str, Any]]:
    """Training-episode statistics per window of env steps (what the behaviour did).

    For each window ``[start, start + window)``: number of finished episodes, their mean
    length, success and collision rates, and how many followed pi_HF.
    """
    rows = []
    for start in range(0, total_steps, window):
        inside = [e for e in episodes if start < e[0] <= start + window]
        n = len(inside)
        rows.append(
            {
                "steps": start + window,
                "episodes": n,
                "hf_episodes": sum(bool(e[4]) for e in inside),
                "mean_length": float(np.mean([e[1] for e in inside])) if n else None,
                "success_rate": float(np.mean([e[2] for e in inside])) if n else None,
                "collision_rate": float(np.mean([e[3] for e in inside])) if n else None,
            }
        )
    return rows


def learn_hf_policy(
    env: gym.Env,
    accuracy: float,
    seed: int,
    n_labels: int,
    *,
    method: str = PAPER_METHOD,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    source: DecodedFeedbackSource | None = None,
    label_channel: str = "hard",
    on_learner: Callable[[FeedbackLearner], None] | None = None,
) -> HFResult:
    """Stage 2 from simulated feedback at accuracy C, on the run's label streams.

    ``method`` is the stage-2 method (:mod:`services.learner.hf_methods`); its label-noise
    model is the known C for both classes (the oracle's truth enters only the noise).
    With a decoded ``source`` (the virtual subject and its decoder) the labels are its own
    and the noise model its held-out per-class recalls; ``label_channel`` says whether Fhat
    reads the hard decisions or the likelihood ratios.

    The labels depend on ``seed`` only (not on method, treatment or PPO settings), so every
    study guides the runs of one seed with the same pi_HF. ``on_label`` is called after
    each label (a job worker checks for cancel there; raising stops the collection),
    ``on_learner`` with the learner after each label's updates (:mod:`services.learner.nstar`).
    """
    return feedback_collection(
        env, accuracy, seed, n_labels, method=method, on_label=on_label, source=source,
        label_channel=label_channel, on_learner=on_learner,
    ).run()  # fmt: skip


def feedback_collection(
    env: gym.Env,
    accuracy: float,
    seed: int,
    n_labels: int,
    *,
    method: str = PAPER_METHOD,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    source: DecodedFeedbackSource | None = None,
    label_channel: str = "hard",
    on_learner: Callable[[FeedbackLearner], None] | None = None,
) -> FeedbackCollection:
    """The stage-2 session of :func:`learn_hf_policy` (same arguments), not yet begun: run
    alone to its end, or in a lockstep batch
    (:func:`~services.learner.feedback_lockstep.collect_feedback_lockstep`)."""
    seeds = RunSeeds(seed)
    good, bad = accuracy, accuracy
    if source is None:
        source = OracleFeedbackSource(accuracy, seed=seeds.int_seed(Stream.LABEL_NOISE))
    else:
        good, bad = source.noise_model
    config = FeedbackConfig(
        method=method, good_accuracy=good, bad_accuracy=bad, label_channel=label_channel
    )
    return FeedbackCollection(
        env,
        source,
        n_labels,
        config,
        RunSeeds(seed).int_seed(Stream.LABEL_COLLECTION),
        default_max_steps(config, n_labels),
        on_label,
        on_learner,
    )


def run_one(
    spec: RunSpec,
    *,
    callback: Callback | None = None,
    checkpoint_path: str | Path | None = None,
    checkpoint_every: int = 10,
    model_path: str | Path | None = None,
    last_model_path: str | Path | None = None,
    hf_policy: HFPolicy | None = None,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    portable: bool = False,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> RunRecord:
    """Execute one run (stage 2 for hf_sparse, then stage 3) and return its record.

    ``callback``, ``checkpoint_path`` and ``checkpoint_every`` go to :func:`train` (a job
    worker reports progress, stops on cancel and resumes from the checkpoint); with
    ``model_path`` the policy of the best evaluation (``record.best_step``) is exported
    there as TorchScript, with ``last_model_path`` the last one; with ``portable``, each also
    as a ``torch.export`` program and ONNX beside it (``.pt2``, ``.onnx``:
    :mod:`~services.learner.policy_files`). A given
    ``hf_policy`` (e.g. learned from a subject's decoded EEG in an online session) guides
    an hf_sparse run instead of stage 2's simulated feedback; ``on_label`` goes to stage 2's
    label collection (see :func:`learn_hf_policy`). A spec with ``virtual_subject`` feedback
    takes its labels from ``feedback_factory(seed, decoder_accuracy)``.
    """
    start = time.perf_counter()
    guidance = run_guidance(
        spec, hf_policy=hf_policy, on_label=on_label, feedback_factory=feedback_factory
    )
    result = train(
        spec.ppo_config(),
        callback,
        hf_policy=guidance.policy,
        checkpoint_path=checkpoint_path,
        checkpoint_every=checkpoint_every,
    )
    export_policies(result, model_path, last_model_path, portable=portable)
    return run_record(spec, result, guidance, time.perf_counter() - start)


def export_policies(
    result: TrainResult,
    model_path: str | Path | None,
    last_model_path: str | Path | None,
    *,
    portable: bool,
) -> None:
    """Export a trained run's best policy to ``model_path`` and its last to
    ``last_model_path`` (each if given) as TorchScript, with ``portable`` also as a
    ``torch.export`` program and ONNX beside it."""
    if model_path is not None:
        result.export_torchscript(model_path, which="best")
        if portable:
            write_beside_torchscript(result.best_policy(), Path(model_path))
    if last_model_path is not None:
        result.export_torchscript(last_model_path, which="last")
        if portable:
            write_beside_torchscript(result.agent, Path(last_model_path))


def run_lockstep(
    specs: Sequence[RunSpec],
    *,
    callbacks: Sequence[Callback | None] | None = None,
    checkpoint_paths: Sequence[str | Path | None] | None = None,
    checkpoint_every: int = 10,
    hf_policies: Sequence[HFPolicy | None] | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    model_paths: Sequence[str | Path | None] | None = None,
    last_model_paths: Sequence[str | Path | None] | None = None,
    portable: bool = False,
) -> list[RunRecord | RunFailure]:
    """Execute runs whose PPO settings allow one lockstep batch
    (:func:`~services.learner.ppo.lockstep.lockstep_key`): stage 2 of the hf_sparse runs in
    lockstep too (:func:`run_guidances`), then stage 3 of all together
    (:func:`train_lockstep`). Each run's record is the one :func:`run_one` gives
    (bit-identical but for ``wall_seconds``: its stage 2 batch's plus the stage 3 batch's);
    a run that raises is a :class:`RunFailure` and the others go on.
    ``callbacks``, ``checkpoint_paths``, given ``hf_policies``, ``model_paths`` and
    ``last_model_paths`` are per run, ``on_label`` and ``portable`` for every run (as
    :func:`run_one`'s; an ``on_label`` that raises ends stage 2 of every run it raised in)."""
    n = len(specs)
    check_one_shape([spec.ppo_config() for spec in specs])  # before stage 2's minutes
    callbacks = list(callbacks) if callbacks is not None else [None] * n
    paths = list(checkpoint_paths) if checkpoint_paths is not None else [None] * n
    given = list(hf_policies) if hf_policies is not None else [None] * n
    models = list(model_paths) if model_paths is not None else [None] * n
    last_models = list(last_model_paths) if last_model_paths is not None else [None] * n
    outcomes: list[RunRecord | RunFailure | None] = [None] * n
    guided: list[tuple[int, RunGuidance]] = []
    guidances = run_guidances(
        specs, hf_policies=given, feedback_factory=feedback_factory, on_label=on_label
    )
    for i, (spec, guidance) in enumerate(zip(specs, guidances, strict=True)):
        if isinstance(guidance, Exception):  # this run fails, the others go on
            outcomes[i] = RunFailure.from_exception(spec, guidance)
        else:
            guided.append((i, guidance))
    start = time.perf_counter()
    results = train_lockstep(
        [specs[i].ppo_config() for i, _ in guided],
        callbacks=[callbacks[i] for i, _ in guided],
        hf_policies=[guidance.policy for _, guidance in guided],
        checkpoint_paths=[paths[i] for i, _ in guided],
        checkpoint_every=checkpoint_every,
    )
    training_seconds = time.perf_counter() - start
    for (i, guidance), result in zip(guided, results, strict=True):
        if isinstance(result, Exception):
            outcomes[i] = RunFailure.from_exception(specs[i], result)
            continue
        try:
            export_policies(result, models[i], last_models[i], portable=portable)
        except Exception as exc:  # this run fails, the others go on
            outcomes[i] = RunFailure.from_exception(specs[i], exc)
            continue
        wall = guidance.seconds + training_seconds
        outcomes[i] = run_record(specs[i], result, guidance, wall)
    return [o for o in outcomes if o is not None]


@dataclass(frozen=True)
class RunGuidance:
    """A run's pi_HF (None for the RL methods), its greedy SPL on the evaluation starts,
    stage 2's summary (None unless it ran) and the seconds it took."""

    policy: HFPolicy | None
    spl: float | None
    summary: dict[str, Any] | None
    seconds: float
    source: DecodedFeedbackSource | None = None
    """The decoded feedback source stage 2 took its labels from (None: the noisy oracle)."""


def run_guidance(
    spec: RunSpec,
    *,
    hf_policy: HFPolicy | None = None,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> RunGuidance:
    """The pi_HF that guides a run: ``hf_policy`` if given, else stage 2's from simulated
    feedback for hf_sparse (:func:`learn_hf_policy`; for ``virtual_subject`` feedback from
    ``feedback_factory``'s source), else none; measured on the run's evaluation starts
    before RL."""
    start = time.perf_counter()
    config = spec.ppo_config()
    if hf_policy is not None:
        with closing(gym.make(config.env_id, **config.env_kwargs)) as eval_env:
            spl = evaluate_spl(eval_env, hf_policy.act, config.eval_seeds)
        return RunGuidance(hf_policy, spl, None, time.perf_counter() - start)
    if spec.method != "hf_sparse":
        return RunGuidance(None, None, None, 0.0)
    source = decoded_source(spec.feedback, spec.seed, spec.decoder_accuracy, feedback_factory)
    with closing(gym.make(config.env_id, **config.env_kwargs)) as label_env:
        hf = learn_hf_policy(
            label_env,
            spec.accuracy,  # type: ignore[arg-type]  # None only with a source
            spec.seed,
            spec.n_labels,
            method=spec.hf_method or PAPER_METHOD,
            on_label=on_label,
            source=source,
            label_channel=spec.label_channel,
        )
        spl = evaluate_spl(label_env, hf.policy.act, config.eval_seeds)
    return RunGuidance(hf.policy, spl, hf.summary(), time.perf_counter() - start, source)


def run_guidances(
    specs: Sequence[RunSpec],
    *,
    hf_policies: Sequence[HFPolicy | None] | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
    on_label: Callable[[FeedbackRecord], None] | None = None,
) -> list[RunGuidance | Exception]:
    """:func:`run_guidance` of every spec (a given pi_HF per spec or None), with the
    stage-2 sessions of the hf_sparse runs in lockstep batches of one batched method
    (:func:`~services.learner.feedback_lockstep.collect_feedback_lockstep`; the others
    alone): each run's guidance is bit-identical to :func:`run_guidance`'s (``seconds``
    aside: the batch's), or the exception its run raised (the others go on). ``on_label``
    is called after each label of every session (raising ends that session)."""
    given = list(hf_policies) if hf_policies is not None else [None] * len(specs)
    outcomes: list[RunGuidance | Exception | None] = [None] * len(specs)
    collections: dict[int, tuple[FeedbackCollection, DecodedFeedbackSource | None]] = {}
    with ExitStack() as envs:
        for i, spec in enumerate(specs):
            try:
                if given[i] is not None or spec.method != "hf_sparse":
                    outcomes[i] = run_guidance(spec, hf_policy=given[i])
                    continue
                config = spec.ppo_config()
                source = decoded_source(
                    spec.feedback, spec.seed, spec.decoder_accuracy, feedback_factory
                )
                env = envs.enter_context(closing(gym.make(config.env_id, **config.env_kwargs)))
                collection = feedback_collection(
                    env,
                    spec.accuracy,  # type: ignore[arg-type]  # None only with a source
                    spec.seed,
                    spec.n_labels,
                    method=spec.hf_method or PAPER_METHOD,
                    on_label=on_label,
                    source=source,
                    label_channel=spec.label_channel,
                )
            except Exception as exc:  # this run fails, the others go on
                outcomes[i] = exc
                continue
            collections[i] = collection, source
        start = time.perf_counter()
        learned = _learn({i: collection for i, (collection, _) in collections.items()})
        for i, hf in learned.items():
            if isinstance(hf, Exception):
                outcomes[i] = hf
                continue
            try:
                config = specs[i].ppo_config()
                spl = evaluate_spl(collections[i][0].env, hf.policy.act, config.eval_seeds)
            except Exception as exc:
                outcomes[i] = exc
                continue
            seconds = time.perf_counter() - start
            outcomes[i] = RunGuidance(hf.policy, spl, hf.summary(), seconds, collections[i][1])
    return [o if o is not None else RuntimeError("run produced no guidance") for o in outcomes]


def _collect_alone(collection: FeedbackCollection) -> HFResult | Exception:
    """A stage-2 session run to its end alone (its exception if it raised)."""
    try:
        return collection.run()
    except Exception as exc:
        return exc


def run_record(
    spec: RunSpec, result: TrainResult, guidance: RunGuidance, wall_seconds: float
) -> RunRecord:
    """The record of a run of ``spec`` trained to ``result``."""
    curve = [[int(step), float(spl)] for step, spl in result.curve]
    return RunRecord(
        task=spec.task,
        method=spec.method,
        accuracy=spec.accuracy,
        seed=spec.seed,
        hf_treatment=spec.hf_treatment,
        curve=curve,
        final_spl=float(result.final_spl),
        hf_policy_spl=guidance.spl,
        wall_seconds=wall_seconds,
        steps_to_0_7=steps_to_reach(curve),
        n_episodes=result.n_episodes,
        n_hf_episodes=result.n_hf_episodes,
        training_episodes=episode_stats(
            result.episodes, result.config.eval_every, result.global_step
        ),
        hf=guidance.summary,
        spec=spec.to_dict(),
        best_step=result.best_step,
        best_spl=float(result.best_spl),
        **feedback_fields(spec.method == "hf_sparse", spec, guidance.source),
        environment=software_environment(),
    )


def decoded_source(
    feedback: str,
    seed: int,
    decoder_accuracy: float | None,
    factory: FeedbackSourceFactory | None,
) -> DecodedFeedbackSource | None:
    """The run's decoded feedback source (None for the noisy oracle's feedback)."""
    if feedback == "oracle":
        return None
    if factory is None:
        raise ValueError(
            f"{feedback} feedback needs a feedback-source factory (bgrl reproduce and "
            "bgrl hf-sweep --feedback virtual_subject supply it)"
        )
    assert decoder_accuracy is not None  # the spec guarantees it
    return factory(seed, decoder_accuracy)


def feedback_fields(
    uses_feedback: bool,
    spec: RunSpec | HFPolicySpec,
    source: DecodedFeedbackSource | None,
) -> dict[str, Any]:
    """The record-format fields of a run's feedback (docs/reproduction.md, "Record format")."""
    if not uses_feedback:
        return {"n_labels": 0}
    return {
        "n_labels": spec.n_labels,
        "feedback": spec.feedback,
        "label_channel": spec.label_channel,
        "decoder_accuracy": None if source is None else source.decoder_accuracy,
        "subject_quality": None if source is None else source.subject_quality,
    }


def software_environment() -> dict[str, str]:
    """Versions of Python and of the packages a run's numbers depend on, the machine
    architecture and the vector instructions torch's CPU kernels use (``cpu_capability``,
    e.g. AVX2 or AVX512: kernels of different widths round differently).

    Float results (and so, through sampling, whole trajectories) change with these, so a
    record can only be repeated bit for bit where they match.
    """
    versions = {
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
    }
    for package in ("torch", "numpy", "gymnasium", "pybullet"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


@dataclass(frozen=True)
class HFPolicySpec:
    """One stage-2-alone measurement: task, feedback accuracy C, seed, labels, method (and,
    for the virtual subject's feedback, the target decoder accuracy and the label channel)."""

    task: str
    accuracy: float | None
    seed: int
    n_labels: int = 1000
    method: str = PAPER_METHOD
    feedback: str = "oracle"
    label_channel: str = "hard"
    decoder_accuracy: float | None = None

    def __post_init__(self) -> None:
        if self.task not in TASK_ENV_IDS:
            raise ValueError(f"unknown task {self.task!r}; expected one of {sorted(TASK_ENV_IDS)}")
        check_feedback(True, self.feedback, self.label_channel)
        check_decoder_accuracy(self.feedback, self.decoder_accuracy)
        if (self.feedback == "oracle") != (self.accuracy is not None):
            raise ValueError("accuracy is required with the oracle's feedback, None otherwise")
        if self.accuracy is not None and not 0.0 <= self.accuracy <= 1.0:
            raise ValueError(f"accuracy must be in [0, 1], got {self.accuracy}")
        if self.seed < 0 or self.n_labels < 1:
            raise ValueError("seed must be >= 0 and n_labels >= 1")
        get_method(self.method)

    @property
    def key(self) -> tuple[Any, ...]:
        """Identity inside a sweep (what resuming matches on; the oracle's keys are those
        of sweeps made before other feedback existed)."""
        key = (self.task, self.accuracy, self.seed, self.n_labels, self.method)
        if self.feedback == "oracle":
            return key
        return (*key, self.feedback, self.label_channel, self.decoder_accuracy)

    @property
    def label(self) -> str:
        """E.g. ``vssg C=0.7 seed=3 labels=1000 paper``."""
        feedback = (
            f"C={self.accuracy:g}"
            if self.accuracy is not None
            else f"subject@{self.decoder_accuracy:g} {self.label_channel}"
        )
        return f"{self.task} {feedback} seed={self.seed} labels={self.n_labels} {self.method}"

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)


def hf_policy_run(
    spec: HFPolicySpec, feedback_factory: FeedbackSourceFactory | None = None
) -> dict[str, Any]:
    """Stage 2 alone: train pi_HF from simulated feedback and measure it (no RL).

    Reports the greedy pi_HF's SPL on the task's evaluation starts (what guides RL), the
    success rate of the *sampling* pi_HF (softmax(beta * sigmoid(Fhat)), 20 episodes from
    the first 20 evaluation starts) and Fhat's validation accuracies: one ``runs`` row of
    ``hf_policies.json``. A spec with ``virtual_subject`` feedback takes its labels from
    ``feedback_factory`` (as :func:`run_one`).
    """
    [row] = _hf_policy_outcomes([spec], feedback_factory, lockstep=False)
    if isinstance(row, Exception):
        raise row
    return row


def hf_policy_runs(
    specs: Sequence[HFPolicySpec],
    feedback_factory: FeedbackSourceFactory | None = None,
    *,
    lockstep: bool = True,
) -> list[dict[str, Any] | RunFailure]:
    """:func:`hf_policy_run` of every spec: with ``lockstep``, the sessions of one batched
    stage-2 method learn together
    (:func:`~services.learner.feedback_lockstep.collect_feedback_lockstep`; the same rows
    bit for bit, ``wall_seconds`` aside: the batch's). A run that raises is a
    :class:`RunFailure`, the others go on."""
    outcomes = _hf_policy_outcomes(specs, feedback_factory, lockstep=lockstep)
    return [
        RunFailure.from_exception(spec, outcome) if isinstance(outcome, Exception) else outcome
        for spec, outcome in zip(specs, outcomes, strict=True)
    ]


def _hf_policy_outcomes(
    specs: Sequence[HFPolicySpec],
    feedback_factory: FeedbackSourceFactory | None,
    *,
    lockstep: bool,
) -> list[dict[str, Any] | Exception]:
    """Each spec's ``hf_policies.json`` row, or the exception its run raised."""
    start = time.perf_counter()
    outcomes: list[dict[str, Any] | Exception | None] = [None] * len(specs)
    collections: dict[int, tuple[FeedbackCollection, DecodedFeedbackSource | None]] = {}
    with ExitStack() as envs:
        for i, spec in enumerate(specs):
            try:
                source = decoded_source(
                    spec.feedback, spec.seed, spec.decoder_accuracy, feedback_factory
                )
                env = envs.enter_context(
                    closing(gym.make(TASK_ENV_IDS[spec.task], reward_mode="sparse"))
                )
                collection = feedback_collection(
                    env,
                    spec.accuracy,  # type: ignore[arg-type]  # None only with a source
                    spec.seed,
                    spec.n_labels,
                    method=spec.method,
                    source=source,
                    label_channel=spec.label_channel,
                )
                collections[i] = collection, source
            except Exception as exc:  # this run fails, the others go on
                outcomes[i] = exc
        learned = _learn(
            {i: collection for i, (collection, _) in collections.items()}, lockstep=lockstep
        )
        for i, hf in learned.items():
            spec, (collection, source) = specs[i], collections[i]
            try:
                if isinstance(hf, Exception):
                    raise hf
                outcomes[i] = _hf_policy_row(spec, hf, collection.env, source, start)
            except Exception as exc:
                outcomes[i] = exc
    return [o if o is not None else RuntimeError("run produced no row") for o in outcomes]


def _learn(
    collections: Mapping[int, FeedbackCollection], *, lockstep: bool = True
) -> dict[int, HFResult | Exception]:
    """Run stage-2 sessions to their ends: those of one batched method together in
    lockstep (with ``lockstep``), the others alone; each one's outcome by its key."""
    groups: dict[str | None, list[int]] = {}
    for i, collection in collections.items():
        key = lockstep_feedback_key(collection.config) if lockstep else None
        groups.setdefault(key, []).append(i)
    outcomes: dict[int, HFResult | Exception] = {}
    for key, members in groups.items():
        batch = [collections[i] for i in members]
        results = (
            [_collect_alone(c) for c in batch] if key is None else collect_feedback_lockstep(batch)
        )
        outcomes |= dict(zip(members, results, strict=True))
    return outcomes


def _hf_policy_row(
    spec: HFPolicySpec,
    hf: HFResult,
    env: gym.Env,
    source: DecodedFeedbackSource | None,
    start: float,
) -> dict[str, Any]:
    """The ``hf_policies.json`` row of ``spec``'s learned pi_HF, measured on ``env``."""
    policy = hf.policy
    greedy_spl = evaluate_spl(env, policy.act, eval_seeds(spec.task, N_VSSG_EVAL_STARTS))
    rng = RunSeeds(spec.seed).generator(Stream.HF_PROBE)
    sampled = [
        run_episode(env, lambda o: policy.act(o, rng), reset_seed)[0]
        for reset_seed in evaluation_reset_seeds(N_HF_PROBE_EPISODES)
    ]
    return {
        "task": spec.task,
        "accuracy": spec.accuracy,
        "seed": spec.seed,
        "method": spec.method,
        "greedy_spl": greedy_spl,
        "sampled_success_rate": float(np.mean(sampled)),
        **hf.summary(),
        **feedback_fields(True, spec, source),
        "decoder_accuracy_target": spec.decoder_accuracy,
        "wall_seconds": time.perf_counter() - start,
    }
