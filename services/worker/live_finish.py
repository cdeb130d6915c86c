"""The end of a live run: the calibration recording and its ``eeg_calibration`` job, the test
accuracy, the online session's HF model (registered as an ``hf_models`` row)."""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select

from services.core.artifacts import CHUNK_BYTES, ArtifactStore, sha256_file
from services.core.db.base import utcnow
from services.core.db.live import LiveDecision, LiveMarker, LiveRun
from services.core.db.models import Artifact, FeedbackLabel, HFModel, Job, Recording
from services.core.live import LiveOptions
from services.core.queue import enqueue_job
from services.eeg.recordings.io import read_recording
from services.eeg.service.settings import EEGSettings
from services.platform.jobs import EEG_CALIBRATION
from services.worker.live_services import ServiceClient
from services.worker.runtime import JobContext

logger = logging.getLogger(__name__)


class RunFinish:
    """The end of one live run: its calibration recording and ``eeg_calibration`` job, its test
    accuracy or its online session's HF model. Every step is idempotent, so an attempt that
    resumes an interrupted finish completes it without a second file, row or job.

    Parameters
    ----------
    context : JobContext
        The run's ``live_session`` job.
    run_id, session_id : int
        The live run and its lab session.
    options : LiveOptions
        The run's options.
    services : mapping of str to ServiceClient
        Clients of the sim, EEG and learner services.
    set_run : callable
        Writes columns of the run's row (``set_run(hf_model_id=...)``).
    """

    def __init__(
        self,
        context: JobContext,
        run_id: int,
        session_id: int,
        options: LiveOptions,
        services: Mapping[str, ServiceClient],
        set_run: Callable[..., None],
    ) -> None:
        self.context = context
        self.runtime = context.runtime
        self.run_id = run_id
        self.session_id = session_id
        self.options = options
        self.services = services
        self.set_run = set_run

    def _markers(self) -> list[LiveMarker]:
        with self.runtime.sessions() as db:
            rows = db.scalars(
                select(LiveMarker).where(LiveMarker.run_id == self.run_id).order_by(LiveMarker.step)
            ).all()
            db.expunge_all()
        return list(rows)

    def _decisions(self) -> list[LiveDecision]:
        with self.runtime.sessions() as db:
            rows = db.scalars(
                select(LiveDecision)
                .where(LiveDecision.run_id == self.run_id)
                .order_by(LiveDecision.step)
            ).all()
            db.expunge_all()
        return list(rows)

    def calibration_relpath(self) -> str:
        """Where a calibration run's recording goes in the artifact store: fixed by the run, so
        an attempt that resumes the finish finds the file an interrupted one stored."""
        return f"recording/live-run-{self.run_id}/session-{self.session_id}-calibration.bdf"

    def stored_calibration_recording(self, recording_name: str) -> dict[str, Any] | None:
        """The EEG service's stored recording of this calibration run (``RecordingPublic``) if
        an earlier attempt had it stored (``DELETE /live/recording`` answered), else None.

        Found through the run's recording row, else (the attempt ended before writing it) by
        its name among the EEG service's recordings stored since the run was created.
        """
        eeg = self.services["eeg"]
        with self.runtime.sessions() as db:
            run = db.get(LiveRun, self.run_id)
            assert run is not None
            created = run.created_at
            sha = (
                db.scalar(select(Recording.sha256).where(Recording.id == run.recording_id))
                if run.recording_id is not None
                else None
            )
        if sha is not None:
            return dict(eeg.call("GET", f"/recordings/{sha}"))
        filename = f"{recording_name}.bdf"
        since = created.astimezone(UTC).replace(microsecond=0)
        found = [
            r
            for r in eeg.call("GET", "/recordings")
            if r["filename"] == filename and datetime.fromisoformat(r["uploaded_at"]) >= since
        ]
        return dict(max(found, key=lambda r: r["uploaded_at"])) if found else None

    def recording_rows(self, stored: dict[str, Any], relpath: str, size: int) -> tuple[int, str]:
        """The run's recording and its ``eeg_calibration`` job: (recording id, job id). Written
        in one transaction with the artifact row and the run's links to both, unless the run
        already links them (an earlier attempt wrote them)."""
        with self.runtime.sessions() as db:
            run = db.get(LiveRun, self.run_id)
            assert run is not None
            if run.recording_id is not None and run.follow_up_job_id is not None:
                return run.recording_id, run.follow_up_job_id
        checked = read_recording(self.runtime.store.path(relpath))
        options = self.options
        with self.runtime.sessions() as db:
            artifact = db.scalar(select(Artifact).where(Artifact.relpath == relpath))
            if artifact is None:
                artifact = Artifact(
                    kind="recording",
                    relpath=relpath,
                    sha256=stored["sha256"],
                    size_bytes=size,
                    owner_id=self.context.submitter_id,
                    job_id=self.context.job_id,
                )
                db.add(artifact)
                db.flush()
            recording = Recording(
                session_id=self.session_id,
                artifact_id=artifact.id,
                filename=relpath.rsplit("/", 1)[-1],
                sha256=stored["sha256"],
                size_bytes=size,
                synthetic=bool(stored["synthetic"]),
                n_channels=len(checked.ch_names),
                channels=list(checked.ch_names),
                sfreq=float(checked.info["sfreq"]),
                duration_s=float(checked.times[-1]),
                validation_status="valid",
                validated_at=utcnow(),
                uploaded_by_id=self.context.submitter_id,
            )
            db.add(recording)
            db.flush()
            config: dict[str, Any] = {"recording_id": recording.id, "seed": options.seed}
            if options.calibration_max_passes is not None:
                config["max_passes"] = options.calibration_max_passes
            job = Job(
                kind=EEG_CALIBRATION.name,
                config=config,
                status="queued",
                submitter_id=self.context.submitter_id,
                max_attempts=self.context.max_attempts,
            )
            db.add(job)
            db.flush()
            run = db.get(LiveRun, self.run_id)
            assert run is not None
            run.recording_id, run.follow_up_job_id = recording.id, job.id
            db.commit()
            return recording.id, job.id

    def send_if_queued(self, job_id: str) -> None:
        """Send the follow-up job to the workers while it is still queued (again, after a crash
        between its row and the send: a duplicate message is dropped by the job's claim)."""
        with self.runtime.sessions() as db:
            status = db.scalar(select(Job.status).where(Job.id == job_id))
        if status == "queued":
            enqueue_job(self.runtime.celery, job_id, EEG_CALIBRATION.name)

    def calibration(self, stored: dict[str, Any] | None) -> dict[str, Any]:
        """Store the EEG service's live recording of the session (BDF + sha256, an artifact and
        a recording row) and start ``eeg_calibration`` on it.

        Idempotent, so a crash at any step is completed by the resumed attempt without a
        second copy, row or job: the file goes to the run's fixed place in the artifact store
        (:func:`copy_into_store`), the rows and the run's links to them are one transaction
        (:func:`recording_rows`), and the job is sent while it is queued (:func:`send_if_queued`).
        """
        markers = self._markers()
        if len(markers) < 2 or stored is None:
            return {"actions": len(markers), "recording_id": None, "calibration_job_id": None}
        relpath = self.calibration_relpath()
        source = EEGSettings(data_dir=self.runtime.settings.data_dir).eeg_dir / "recordings"
        # the services share the data folder (bgrl up; one volume in a multi-host deployment)
        size = copy_into_store(
            self.runtime.store, source / f"{stored['id']}.bdf", relpath, stored["sha256"]
        )
        recording_id, job_id = self.recording_rows(stored, relpath, size)
        self.send_if_queued(job_id)
        return {
            "actions": len(markers),
            "errors": sum(1 for m in markers if m.oracle_correct is False),
            "recording_id": recording_id,
            "recording_sha256": stored["sha256"],
            "recorded_markers": stored["n_actions"],
            "recording_duration_s": stored["duration_s"],
            "calibration_job_id": job_id,
        }

    def test(self, done: int) -> dict[str, Any]:
        """The decoder's final accuracy against the oracle's labels."""
        return {"actions": done, **decoding_accuracy(self._decisions())}

    def online(self, done: int, hf_session_id: str | None) -> dict[str, Any]:
        """Export pi_HF into the artifact store and register it as an HF model."""
        exported = self.services["learner"].call(
            "POST", f"/hf-sessions/{hf_session_id}/export", json={}
        )
        decoding = decoding_accuracy(self._decisions())
        files = exported["files"]
        with self.runtime.sessions() as db:
            n_labels = (
                db.query(FeedbackLabel).filter(FeedbackLabel.session_id == self.session_id).count()
            )
            artifacts = {
                fmt: Artifact(
                    kind="model",
                    relpath=stored["relpath"],
                    sha256=stored["sha256"],
                    size_bytes=stored["size_bytes"],
                    owner_id=self.context.submitter_id,
                    job_id=self.context.job_id,
                )
                for fmt, stored in files.items()
            }
            db.add_all(artifacts.values())
            db.flush()
            model = HFModel(
                name=f"session {self.session_id} pi_HF ({n_labels} labels)",
                task=self.options.task,
                feedback_accuracy=decoding["accuracy"],
                n_labels=n_labels,
                session_id=self.session_id,
                job_id=self.context.job_id,
                torchscript_artifact_id=artifacts["torchscript"].id,
                pt2_artifact_id=artifacts["pt2"].id,
                onnx_artifact_id=artifacts["onnx"].id,
                metrics={
                    **(exported.get("metrics") or {}),
                    "model_version": exported["model_version"],
                },
            )
            db.add(model)
            db.commit()
            model_id = model.id
        self.set_run(hf_model_id=model_id)
        spl = hf_policy_spl(
            self.runtime.store.path(files["torchscript"]["relpath"]), self.options.task
        )
        with self.runtime.sessions() as db:
            row = db.get(HFModel, model_id)
            assert row is not None
            row.metrics = {**row.metrics, "hf_policy_spl": spl}
            db.commit()
        return {
            "actions": done,
            "labels": n_labels,
            "label_channel": self.options.label_channel,
            "hf_model_id": model_id,
            "hf_policy_spl": spl,
            **{f"decoding_{k}": v for k, v in decoding.items()},
        }


def copy_into_store(store: ArtifactStore, source: Path, relpath: str, sha256: str) -> int:
    """Copy ``source`` to ``relpath`` in the store unless it is already there with
    ``sha256``; returns its size. The copy is hashed as it is written into a locked part
    (:meth:`ArtifactStore.open_part`: an interrupted copy's part is removed at the api's next
    start), synced, checked against ``sha256`` and renamed into place: the file is complete
    or absent."""
    target = store.path(relpath)
    if target.is_file() and sha256_file(target) == sha256:
        return target.stat().st_size
    part, dst = store.open_part()
    digest = hashlib.sha256()
    try:
        with source.open("rb") as src:
            while chunk := src.read(CHUNK_BYTES):
                digest.update(chunk)
                dst.write(chunk)
        dst.flush()
        os.fsync(dst.fileno())
        if digest.hexdigest() != sha256:
            raise RuntimeError(
                f"{source.name}: the copy's sha256 {digest.hexdigest()[:12]} is not {sha256[:12]}"
            )
        store.make_folders(target.parent)
        os.replace(part, target)
    except BaseException:
        part.unlink(missing_ok=True)
        raise
    finally:
        dst.close()  # after the rename: the part stays locked while it is one
    return target.stat().st_size


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
