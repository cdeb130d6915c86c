"""The end of a live run: the calibration recording and its ``eeg_calibration`` job, the test
accuracy, the online session's HF model (registered as an ``hf_models`` row)."""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import select

from services.core.db.live import LiveDecision, LiveMarker
from services.core.db.models import Artifact, FeedbackLabel, HFModel, Job, Recording
from services.core.queue import enqueue_job
from services.eeg.io import file_sha256, read_recording
from services.eeg.settings import EEGSettings

if TYPE_CHECKING:
    from services.worker.live_session import LiveRunner

logger = logging.getLogger(__name__)


def _markers(runner: LiveRunner) -> list[LiveMarker]:
    with runner.runtime.sessions() as db:
        rows = db.scalars(
            select(LiveMarker).where(LiveMarker.run_id == runner.run_id).order_by(LiveMarker.step)
        ).all()
        db.expunge_all()
    return list(rows)


def _decisions(runner: LiveRunner) -> list[LiveDecision]:
    with runner.runtime.sessions() as db:
        rows = db.scalars(
            select(LiveDecision)
            .where(LiveDecision.run_id == runner.run_id)
            .order_by(LiveDecision.step)
        ).all()
        db.expunge_all()
    return list(rows)


def finish_calibration(runner: LiveRunner) -> dict[str, Any]:
    """Store the EEG service's live recording of the session (BDF + sha256, a recording
    row) and start ``eeg_calibration`` on it."""
    markers = _markers(runner)
    stored = runner.stored_recording
    if len(markers) < 2 or stored is None:
        return {"actions": len(markers), "recording_id": None, "calibration_job_id": None}
    options = runner.options
    name = f"session-{runner.session_id}-calibration.bdf"
    source = EEGSettings(data_dir=runner.runtime.settings.data_dir).eeg_dir / "recordings"
    with tempfile.TemporaryDirectory(prefix="bgrl-live-") as tmp:
        path = Path(tmp) / name
        shutil.copyfile(source / f"{stored['id']}.bdf", path)  # the services share the folder
        sha = file_sha256(path)
        if sha != stored["sha256"]:
            raise RuntimeError(
                f"live recording {stored['id'][:12]}: the copy's sha256 {sha[:12]} differs"
            )
        checked = read_recording(path)
        artifact_id = runner.context.store_file(path, kind="recording", name=name)
    with runner.runtime.sessions() as db:
        size = db.scalar(select(Artifact.size_bytes).where(Artifact.id == artifact_id))
        recording = Recording(
            session_id=runner.session_id,
            artifact_id=artifact_id,
            filename=name,
            sha256=sha,
            size_bytes=int(size or 0),
            synthetic=bool(stored["synthetic"]),
            n_channels=len(checked.ch_names),
            channels=list(checked.ch_names),
            sfreq=float(checked.info["sfreq"]),
            duration_s=float(checked.times[-1]),
            validation_status="valid",
            uploaded_by_id=runner.context.submitter_id,
        )
        db.add(recording)
        db.flush()
        config: dict[str, Any] = {"recording_id": recording.id, "seed": options.seed}
        if options.calibration_max_passes is not None:
            config["max_passes"] = options.calibration_max_passes
        job = Job(
            kind="eeg_calibration",
            config=config,
            status="queued",
            submitter_id=runner.context.submitter_id,
            max_attempts=runner.context.max_attempts,
        )
        db.add(job)
        db.commit()
        recording_id, job_id = recording.id, job.id
    runner._set_run(recording_id=recording_id, follow_up_job_id=job_id)
    enqueue_job(runner.runtime.celery, job_id, "eeg_calibration")
    n_errors = sum(1 for m in markers if m.oracle_correct is False)
    return {
        "actions": len(markers),
        "errors": n_errors,
        "recording_id": recording_id,
        "recording_sha256": sha,
        "recorded_markers": stored["n_actions"],
        "recording_duration_s": stored["duration_s"],
        "calibration_job_id": job_id,
    }


def decoding_accuracy(decisions: list[LiveDecision]) -> dict[str, Any]:
    """Accepted/rejected counts and the accuracy of accepted decisions vs the oracle."""
    accepted = [d for d in decisions if d.status == "ok" and d.oracle_correct is not None]
    hits = sum(1 for d in accepted if (d.feedback == "correct") == d.oracle_correct)
    return {
        "decisions": len(decisions),
        "accepted": len(accepted),
        "rejected": sum(1 for d in decisions if d.status == "rejected"),
        "lost": sum(1 for d in decisions if (d.reason or "").startswith("lost")),
        "accuracy": hits / len(accepted) if accepted else None,
    }


def finish_test(runner: LiveRunner) -> dict[str, Any]:
    """The decoder's final accuracy against the oracle's labels."""
    return {"actions": runner.done, **decoding_accuracy(_decisions(runner))}


def finish_online(runner: LiveRunner) -> dict[str, Any]:
    """Export pi_HF into the artifact store and register it as an HF model."""
    exported = runner.services["learner"].call(
        "POST", f"/hf-sessions/{runner.hf_session_id}/export", json={}
    )
    decoding = decoding_accuracy(_decisions(runner))
    with runner.runtime.sessions() as db:
        n_labels = (
            db.query(FeedbackLabel).filter(FeedbackLabel.session_id == runner.session_id).count()
        )
        artifact = Artifact(
            kind="model",
            relpath=exported["relpath"],
            sha256=exported["sha256"],
            size_bytes=exported["size_bytes"],
            owner_id=runner.context.submitter_id,
            job_id=runner.context.job_id,
        )
        db.add(artifact)
        db.flush()
        model = HFModel(
            name=f"session {runner.session_id} pi_HF ({n_labels} labels)",
            task=runner.options.task,
            feedback_accuracy=decoding["accuracy"],
            n_labels=n_labels,
            session_id=runner.session_id,
            job_id=runner.context.job_id,
            torchscript_artifact_id=artifact.id,
            metrics={**(exported.get("metrics") or {}), "model_version": exported["model_version"]},
        )
        db.add(model)
        db.commit()
        model_id = model.id
    runner._set_run(hf_model_id=model_id)
    spl = hf_policy_spl(runner.runtime.store.path(exported["relpath"]), runner.options.task)
    with runner.runtime.sessions() as db:
        row = db.get(HFModel, model_id)
        assert row is not None
        row.metrics = {**row.metrics, "hf_policy_spl": spl}
        db.commit()
    return {
        "actions": runner.done,
        "labels": n_labels,
        "hf_model_id": model_id,
        "hf_policy_spl": spl,
        **{f"decoding_{k}": v for k, v in decoding.items()},
    }


def hf_policy_spl(model_path: Path, task: str) -> float:
    """SPL of the exported greedy pi_HF over the learner's evaluation seeds."""
    from contextlib import closing

    import gymnasium as gym
    import torch

    from services.learner.evaluation import evaluate_spl
    from services.learner.specs import RunSpec

    module = torch.jit.load(str(model_path), map_location="cpu")
    config = RunSpec(task=task, method="rl_sparse", seed=0).ppo_config()

    def act(obs: np.ndarray) -> int:
        with torch.no_grad():
            return int(module.act(torch.as_tensor(np.asarray(obs, dtype=np.float32))))

    with closing(gym.make(config.env_id, **config.env_kwargs)) as env:
        return evaluate_spl(env, act, config.eval_seeds)
