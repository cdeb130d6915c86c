"""Training jobs: ``guided_ppo`` (one run submitted on its own) and ``reproduce_run`` (one
run of a reproduction). Both execute the learner's run (stage 2 for HF+sparse, then guided
PPO, Akinola et al. 2020, Algorithm 1) with progress, the SPL curve and checkpoints written
to the job, and store the trained policy (TorchScript, a ``torch.export`` program and ONNX,
each with its observation normalisation) as the job's model: the policy of the best
evaluation (as SB3's ``EvalCallback`` keeps), whose step and SPL the result gives as
``best_step`` / ``best_spl``; the last policy is a second artifact,
``last_model_artifact_id`` in the result (``/api/v1/artifacts/{id}/download``), and
``last_model_artifact_ids`` names it in every format.

TensorBoard: every update's metrics (CleanRL's names: ``losses/value_loss``,
``charts/episodic_return``, ``charts/SPS``, ...) and every evaluation's SPL
(``charts/SPL``) are written as TensorBoard event files to ``tensorboard/job-<id>/`` in the
artifact store as the job runs (``GET /api/v1/jobs/{id}/tensorboard`` zips them; view with
``tensorboard --logdir``). A resumed attempt adds its own event file there.

Resume: the checkpoint lives in the artifact store at ``checkpoint/job-<id>/checkpoint.pt``.
A job claimed again (after its worker died, or a failed attempt) finds it there and the
learner resumes from it; the learner's resume is exact, so the job ends with the same result
as an uninterrupted run of that seed.
"""

from __future__ import annotations

import hashlib
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from sqlalchemy import select
from torch.utils.tensorboard import SummaryWriter

from services.core.artifacts import TENSORBOARD_KIND
from services.core.db.models import Artifact, HFModel
from services.core.model_formats import MODEL_FORMATS, SUFFIXES, ModelFormat
from services.learner.feedback import HFPolicy
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.learner.ppo import Callback
from services.learner.runs import RunRecord, run_one
from services.learner.specs import RunSpec, apply_preset
from services.platform.jobs import GUIDED_PPO
from services.platform.jobs.guided_ppo import GuidedPPOConfig
from services.sim.maps import DEFAULT_MAP_PATH, load_map
from services.sim.oracle import Oracle
from services.sim.settings import SimSettings
from services.worker.runtime import JobConfigError, JobContext, JobOutcome, parse_config

PROGRESS_EVERY_S = 1.0
"""Progress (steps done) is written at most this often; every evaluation is written."""
SPL_TAG = "charts/SPL"
"""TensorBoard tag of the greedy policy's SPL at each evaluation."""
TENSORBOARD_FLUSH_S = 5
"""The TensorBoard event files are flushed at least this often (and at every evaluation)."""


class JobProgress(Callback):
    """Writes steps done, progress and the SPL curve to the job row, and every update's
    metrics and evaluation's SPL to ``writer`` (TensorBoard) when given.

    On cancel (or a lost lease) it raises :class:`JobStoppedError` at the next step, which
    leaves training at once: returning False would finish the rollout, the update and the
    policy export first (seconds), and the job is not kept anyway. The latest periodic
    checkpoint stays in the store.
    """

    def __init__(
        self,
        context: JobContext,
        total_steps: int,
        curve: list[list[float]],
        writer: SummaryWriter | None = None,
    ) -> None:
        self.context = context
        self.total_steps = total_steps
        self.curve = curve
        self.writer = writer
        self.last_write = 0.0

    def on_step(self, global_step: int, info: dict[str, Any]) -> bool:
        self.context.check_stop()
        return True

    def on_update(self, global_step: int, metrics: dict[str, float]) -> bool:
        if self.writer is not None:
            for name, value in metrics.items():
                self.writer.add_scalar(name, value, global_step)
        now = time.monotonic()
        if now - self.last_write >= PROGRESS_EVERY_S:
            self.last_write = now
            self.context.update(
                steps_done=global_step, progress=min(global_step / self.total_steps, 0.99)
            )
        return True

    def on_eval(self, global_step: int, spl: float) -> bool:
        if self.writer is not None:
            self.writer.add_scalar(SPL_TAG, spl, global_step)
            self.writer.flush()
        self.curve.append([int(global_step), float(spl)])
        self.context.update(
            steps_done=global_step,
            progress=min(global_step / self.total_steps, 0.99),
            curve=list(self.curve),
        )
        return True


def spec_from_guided_config(config: GuidedPPOConfig) -> RunSpec:
    """The learner's run spec of a ``guided_ppo`` job config."""
    overrides = {**config.ppo.given(), "total_steps": config.total_steps}
    try:  # the platform preset: truncated IS for hf_sparse, its PPO settings for every method
        treatments, overrides, _ = apply_preset(config.preset, [config.hf_treatment], overrides)
        return RunSpec(
            task=config.task,
            method=config.method,
            seed=config.seed,
            accuracy=config.accuracy,
            hf_treatment=treatments[0] if config.method == "hf_sparse" else config.hf_treatment,
            n_labels=config.n_labels,
            ppo_overrides=overrides,
            hf_method=config.hf_method
            or (RECOMMENDED_METHOD if config.method == "hf_sparse" else None),
        )
    except (TypeError, ValueError) as exc:
        raise JobConfigError(str(exc)) from None


def checkpoint_progress(path: Path) -> tuple[int, list[list[float]]]:
    """Env steps and SPL curve stored in a learner checkpoint.

    Read with ``weights_only`` (tensors and plain containers, never code from the file); an
    unreadable checkpoint is a ValueError naming the file (the attempt fails).
    """
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")["state"]
    except Exception as exc:
        raise ValueError(
            f"checkpoint: {path.name} is not a readable checkpoint (truncated or corrupt?): "
            f"{type(exc).__name__}: {str(exc).splitlines()[0][:200] if str(exc) else ''}"
        ) from exc
    return int(state["global_step"]), [[int(s), float(v)] for s, v in state["curve"]]


def weights_sha256(model_path: Path) -> str:
    """SHA-256 over the exported policy's tensors (name and bytes, in name order)."""
    module = torch.jit.load(str(model_path), map_location="cpu")
    digest = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().contiguous().cpu().numpy().tobytes())
    return digest.hexdigest()


def warm_oracle(spec: RunSpec, data_dir: Path) -> None:
    """Load the map's oracle lattice into this process from the disk cache (or build and
    cache it there): the environments of the run then find it in memory instead of
    rebuilding it (seconds) in every worker process."""
    cache_dir = SimSettings(data_dir=data_dir).oracle_cache_dir
    nav_map = load_map(spec.map_path if spec.map_path is not None else DEFAULT_MAP_PATH)
    Oracle.for_map(nav_map, cache_dir)


def stored_hf_policy(context: JobContext, hf_model_id: int) -> tuple[HFPolicy, float | None]:
    """The greedy pi_HF of HF model ``hf_model_id`` (an online session's TorchScript export)
    and the feedback accuracy it was learned with."""
    with context.runtime.sessions() as session:
        row = session.execute(
            select(HFModel.feedback_accuracy, Artifact.relpath)
            .join(Artifact, Artifact.id == HFModel.torchscript_artifact_id)
            .where(HFModel.id == hf_model_id)
        ).first()
    if row is None:
        raise JobConfigError(f"hf_model_id: no HF model {hf_model_id} with a TorchScript file")
    path = context.runtime.store.path(row.relpath)
    if not path.is_file():
        raise JobConfigError(
            f"hf_model_id: the TorchScript file of HF model {hf_model_id} is missing from the "
            "artifact store"
        )
    try:
        module = torch.jit.load(str(path), map_location="cpu")
    except (RuntimeError, ValueError) as exc:
        raise JobConfigError(
            f"hf_model_id: the TorchScript file of HF model {hf_model_id} is not readable: "
            f"{str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__}"
        ) from None
    return HFPolicy(module), row.feedback_accuracy


def train_spec(
    context: JobContext, spec: RunSpec, checkpoint_every: int, hf_policy: HFPolicy | None = None
) -> JobOutcome:
    """Run ``spec`` for the job, resuming from its checkpoint if one exists."""
    total_steps = spec.ppo_config().total_steps
    warm_oracle(spec, context.runtime.settings.data_dir)
    checkpoint = context.job_dir("checkpoint") / "checkpoint.pt"
    curve: list[list[float]] = []
    if checkpoint.exists():
        step, curve = checkpoint_progress(checkpoint)
        context.update(resumed_from_step=step, steps_done=step, curve=curve)
    context.watch_checkpoint(checkpoint)
    context.check_stop()
    writer = SummaryWriter(str(context.job_dir(TENSORBOARD_KIND)), flush_secs=TENSORBOARD_FLUSH_S)
    with writer, tempfile.TemporaryDirectory(prefix="bgrl-job-") as work_dir:
        model_path = Path(work_dir) / "policy.pt"
        last_model_path = Path(work_dir) / "policy_last.pt"
        record: RunRecord = run_one(
            spec,
            callback=JobProgress(context, total_steps, curve, writer),
            checkpoint_path=checkpoint,
            checkpoint_every=checkpoint_every,
            model_path=model_path,
            last_model_path=last_model_path,
            hf_policy=hf_policy,
            on_label=lambda _record: context.check_stop(),  # cancel during stage 2 too
            portable=True,
        )
        context.check_stop()
        stored, best_ids = store_trained_policies(context, model_path, last_model_path)
    return JobOutcome(
        result={**record.to_dict(), **stored},
        values={
            "model_artifact_id": best_ids["torchscript"],
            "model_pt2_artifact_id": best_ids["pt2"],
            "model_onnx_artifact_id": best_ids["onnx"],
            "curve": record.curve,
            "steps_done": total_steps,
        },
    )


def store_trained_policies(
    context: JobContext, model_path: Path, last_model_path: Path
) -> tuple[dict[str, Any], dict[ModelFormat, str]]:
    """Store a run's best and last policy files (:func:`store_policy_files`): the result's
    fields saying which is the model and where the last one is, and the best one's ids."""
    weights = weights_sha256(model_path)
    last_weights = weights_sha256(last_model_path)
    best_ids = store_policy_files(context, model_path)
    last_ids = store_policy_files(context, last_model_path)
    stored = {
        "model": "best",  # the job's model is the best evaluation's policy
        "weights_sha256": weights,
        "last_model_artifact_id": last_ids["torchscript"],
        "last_model_artifact_ids": last_ids,
        "last_weights_sha256": last_weights,
    }
    return stored, best_ids


def store_policy_files(context: JobContext, torchscript_path: Path) -> dict[ModelFormat, str]:
    """Store a policy's TorchScript file and its ``.pt2`` and ONNX files beside it as the
    job's artifacts; their ids by format."""
    return {
        fmt: context.store_file(path, kind="model", name=path.name)
        for fmt in MODEL_FORMATS
        for path in [torchscript_path.with_suffix(SUFFIXES[fmt])]
    }


def guided_ppo(context: JobContext) -> JobOutcome:
    """Handler of ``guided_ppo`` jobs."""
    config: GuidedPPOConfig = parse_config(GUIDED_PPO, context.config)
    hf_policy = None
    if config.hf_model_id is not None:
        hf_policy, accuracy = stored_hf_policy(context, config.hf_model_id)
        if config.accuracy is None:
            if accuracy is None:
                raise JobConfigError("accuracy: the HF model has no measured feedback accuracy")
            config = config.model_copy(update={"accuracy": round(accuracy, 4)})
    spec = spec_from_guided_config(config)
    every = config.checkpoint_every or context.runtime.settings.checkpoint_every
    return train_spec(context, spec, every, hf_policy)


def reproduce_run(context: JobContext) -> JobOutcome:
    """Handler of ``reproduce_run`` jobs (the config is the learner's run spec)."""
    config = dict(context.config)
    every = config.pop("checkpoint_every", context.runtime.settings.checkpoint_every)
    try:
        spec = RunSpec.from_dict(config)
    except (TypeError, ValueError) as exc:
        raise JobConfigError(f"not a run spec: {exc}") from None
    return train_spec(context, spec, int(every))
