"""``eeg_calibration`` jobs: train the ErrP classifier on a stored calibration recording.

The recording is read from the artifact store, calibrated by the EEG pipeline
(:func:`services.eeg.decoding.calibration.calibrate`), and every file it writes (weights,
TorchScript, .pt2, ONNX, metrics, history, report) becomes an artifact of the job; a
``classifiers`` row links them to the recording and its subject.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from sqlalchemy import select

from services.core.db.models import Artifact, Classifier, LabSession, Recording
from services.core.web import jsonable
from services.eeg.decoding.calibration import TrainingConfig, calibrate
from services.eeg.decoding.classifier import ONNX_FILE, PT2_FILE, TORCHSCRIPT_FILE
from services.eeg.recordings.io import RecordingError, read_recording
from services.platform.jobs import EEG_CALIBRATION
from services.platform.jobs.eeg_calibration import EEGCalibrationConfig
from services.worker.runtime import JobConfigError, JobContext, JobOutcome, parse_config

ARTIFACT_KINDS = {".png": "plot", ".json": "results", ".html": "results"}


def eeg_calibration(context: JobContext) -> JobOutcome:
    """Handler of ``eeg_calibration`` jobs."""
    config: EEGCalibrationConfig = parse_config(EEG_CALIBRATION, context.config)
    recording_id, seed = config.recording_id, config.seed
    max_passes = config.max_passes or TrainingConfig().max_passes
    with context.runtime.sessions() as session:
        row = session.execute(
            select(Recording, Artifact.relpath, LabSession.subject_id)
            .join(Artifact, Artifact.id == Recording.artifact_id)
            .join(LabSession, LabSession.id == Recording.session_id)
            .where(Recording.id == recording_id)
        ).first()
    if row is None:
        raise JobConfigError(f"recording_id: no recording {recording_id}")
    recording, relpath, subject_id = row
    try:
        raw = read_recording(context.runtime.store.path(relpath))
    except (RecordingError, FileNotFoundError) as exc:
        raise JobConfigError(f"recording {recording_id}: {exc}") from None
    context.check_stop()
    with tempfile.TemporaryDirectory(prefix="bgrl-calibration-") as tmp:
        out = Path(tmp)
        try:
            result = calibrate(
                raw,
                seed=seed,
                out_dir=out,
                config=TrainingConfig(max_passes=max_passes),
                report=config.report,
                onnx=config.onnx,
            )
        except ValueError as exc:  # e.g. too few labelled epochs: retrying will not help
            raise JobConfigError(f"recording {recording_id}: {exc}") from None
        context.check_stop()
        artifacts = {
            path.name: context.store_file(
                path, kind=ARTIFACT_KINDS.get(path.suffix, "classifier"), name=path.name
            )
            for path in sorted(out.iterdir())
            if path.is_file()
        }
    metrics = jsonable(dict(result.metrics))
    with context.runtime.sessions() as session:
        classifier = Classifier(
            name=f"{recording.filename} (seed {seed})",
            subject_id=subject_id,
            recording_id=recording_id,
            job_id=context.job_id,
            onnx_artifact_id=artifacts.get(ONNX_FILE),
            torchscript_artifact_id=artifacts.get(TORCHSCRIPT_FILE),
            pt2_artifact_id=artifacts.get(PT2_FILE),
            metrics=metrics,
        )
        session.add(classifier)
        session.commit()
        classifier_id = classifier.id
    return JobOutcome(
        result={"classifier_id": classifier_id, "metrics": metrics, "artifacts": artifacts},
        values={
            "model_artifact_id": artifacts.get(TORCHSCRIPT_FILE),
            "model_pt2_artifact_id": artifacts.get(PT2_FILE),
            "model_onnx_artifact_id": artifacts.get(ONNX_FILE),
        },
    )
