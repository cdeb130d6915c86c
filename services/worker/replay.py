"""``session_replay`` jobs: a stored session replayed through the live decoder and the learner.

The session's EEG (its recording, or the virtual subject's stream regenerated: see
:mod:`services.worker.session_data`) is fed chunk by chunk into the EEG service's own live
decoding path (:class:`~services.eeg.live.ingest.LiveIngest` and
:meth:`LiveSession.decode <services.eeg.service.live_session.LiveSession.decode>`) with a classifier
(the session's own by default, or another one), one decision per stored marker. Every
accepted decision becomes a label of a fresh online HF session
(:class:`~services.learner.service.session.HFSession`, the learner service's own class, with
the original run's task, map, seed and label budget), in step order, on the state and action
stored with the marker. The resulting pi_HF is exported (TorchScript, .pt2, ONNX) as a new
``hf_models`` row linked to the original session, with the comparison: decisions that agree
with the original ones, the label accuracy, both policies' SPL.

With the session's own classifier and an accelerated virtual-subject run, the replay decodes
the same samples with the same code, so its labels are the original's and Fhat is trained
identically (the learner is deterministic given its seed and labels).
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import asdict
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from sqlalchemy import select

from services.core.db.live import LiveRun
from services.core.db.models import Artifact, HFModel
from services.core.markers import ActionMarker
from services.core.model_formats import SUFFIXES
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.live.ingest import LiveIngest
from services.eeg.service.live_session import LiveSession
from services.learner.feedback import FeedbackConfig
from services.learner.hf_methods import PAPER_METHOD
from services.learner.service.export import policy_files
from services.learner.service.session import HFSession, SessionSpec
from services.platform.jobs import SESSION_REPLAY
from services.platform.jobs.session_replay import SessionReplayConfig
from services.sim.registry import resolve_map
from services.worker.live_eeg import EPOCH_END_S
from services.worker.live_finish import hf_policy_spl
from services.worker.runtime import JobConfigError, JobContext, JobOutcome, Runtime, parse_config
from services.worker.session_data import (
    SessionStream,
    StoredSession,
    load_classifier,
    load_session,
    session_stream,
)

logger = logging.getLogger(__name__)


def decode_session(
    stored: StoredSession, stream: SessionStream, classifier: ErrPClassifier, classifier_id: str
) -> dict[int, dict[str, Any]]:
    """One decision per marker with an onset: ``step -> Feedback`` fields, as live."""
    ingest = LiveIngest(
        stream.ch_names,
        stream.sfreq,
        eeg_ch_names=classifier.ch_names,
        params=classifier.params,
    )
    classifier.check_compatible(ingest.eeg_ch_names, stream.sfreq)
    decoder = LiveSession(ingest, classifier, classifier_id, "websocket", synthetic=True)
    pushed_until = -float("inf")
    out: dict[int, dict[str, Any]] = {}
    for row in stored.markers:
        onset = stream.onsets.get(row.step)
        if onset is None:
            continue
        while pushed_until < onset + EPOCH_END_S + 2.0 / stream.sfreq:
            try:
                samples, first = next(stream.chunks)
            except StopIteration:
                break
            ingest.push_chunk(samples, first_timestamp=first)
            pushed_until = first + len(samples) / stream.sfreq
        marker = ActionMarker(
            session_id=row.sim_session_id,
            step=row.sim_step,
            episode=row.episode,
            action=row.action,
            correct=row.oracle_correct,
            timestamp=onset,
        )
        feedback = decoder.decode(ingest.epoch_for(onset), marker)
        out[row.step] = feedback.model_dump(mode="json")
    return out


UNRECORDED_ONLINE_METHOD = "categorical"
"""The learner service's default stage-2 method when live runs did not yet record theirs
(2026-12-01 to 2026-12-02)."""


def _original_method(runtime: Runtime, run: LiveRun) -> str:
    """The stage-2 method the original session trained with: recorded in its HF model (a
    model exported before methods were recorded was the paper's), else in its live run; a
    run from before runs recorded it used the learner's default of then."""
    with runtime.sessions() as db:
        original = db.get(HFModel, run.hf_model_id) if run.hf_model_id else None
        if original is not None:
            return str((original.metrics or {}).get("hf_method", PAPER_METHOD))
    return run.hf_method or UNRECORDED_ONLINE_METHOD


def _hf_session(runtime_data_dir: Path, run: LiveRun, budget: int, method: str) -> HFSession:
    options = run.options
    map_name, map_path, _ = resolve_map(options.get("map"), (), runtime_data_dir / "sim" / "oracle")
    spec = SessionSpec(
        id=f"replay-run-{run.id}",
        task=str(options.get("task", "sssg")),
        map=map_name,
        map_path=str(map_path),
        seed=int(options.get("seed", 0)),
        label_budget=budget,
        method=method,
        fhat=asdict(FeedbackConfig(method=method, label_channel=run.label_channel or "hard")),
        created_at=datetime.now(UTC).replace(microsecond=0),
    )
    return HFSession(spec)


def session_replay(context: JobContext) -> JobOutcome:
    """Handler of ``session_replay`` jobs: config ``{session_id, classifier_id?,
    label_budget?}``."""
    config: SessionReplayConfig = parse_config(SESSION_REPLAY, context.config)
    session_id = config.session_id
    runtime = context.runtime
    stored = load_session(runtime, session_id)
    run = stored.run
    if run is None or not stored.markers:
        raise JobConfigError(f"session_id: session {session_id} has no live run with markers")
    if run.mode != "online":
        raise JobConfigError(
            f"session_id: session {session_id} is a {run.mode} session; replay trains pi_HF "
            "from an online session's states and actions"
        )
    classifier_id = config.classifier_id or run.options.get("classifier_id")
    if classifier_id is None:
        raise JobConfigError("classifier_id: the session has none; give one")
    budget = config.label_budget or int(run.options.get("label_budget", 1000))
    classifier = load_classifier(runtime, int(classifier_id))
    if run.label_channel == "soft" and classifier.calibration is None:
        raise JobConfigError(
            f"classifier_id: classifier {classifier_id} has no calibrated posterior, which "
            "replaying a session on the soft label channel needs"
        )
    stream = session_stream(runtime, stored)
    decisions = decode_session(stored, stream, classifier, f"platform-{classifier_id}")
    context.check_stop()

    hf = _hf_session(runtime.settings.data_dir, run, budget, _original_method(runtime, run))
    labels: list[dict[str, Any]] = []
    for row in stored.markers:
        decision = decisions.get(row.step)
        if decision is None or decision["status"] != "ok" or hf.done:
            continue
        hf.add_label(
            marker_id=f"run{run.id}:{row.step}",
            observation=list(row.observation),
            action=row.action,
            correct=decision["feedback"] == "correct",
            p_error=decision["p_error"],
            log_likelihood_ratio=decision.get("log_likelihood_ratio"),
            oracle_correct=row.oracle_correct,
        )
        labels.append(
            {"step": row.step, "feedback": decision["feedback"], "p_error": decision["p_error"]}
        )
    context.update(progress=0.8)

    compared = [
        (decisions[step], original)
        for step, original in stored.decisions.items()
        if step in decisions
    ]
    same = sum(
        1
        for new, old in compared
        if (new["status"], new.get("feedback")) == (old.status, old.feedback)
    )
    accepted = [d for d in decisions.values() if d["status"] == "ok"]
    by_step = {m.step: m for m in stored.markers}
    hits = sum(
        1
        for step, d in decisions.items()
        if d["status"] == "ok"
        and by_step[step].oracle_correct is not None
        and (d["feedback"] == "correct") == by_step[step].oracle_correct
    )
    known = sum(
        1
        for step, d in decisions.items()
        if d["status"] == "ok" and by_step[step].oracle_correct is not None
    )
    metrics = hf.model_metrics()
    meta = {
        "kind": "hf_policy",
        "replay_of_session": session_id,
        "replay_of_run": run.id,
        "classifier_id": classifier_id,
        "labels": len(labels),
        "model_version": hf.model_version,
        "metrics": metrics,
    }
    artifact_ids: dict[str, str] = {}
    with tempfile.TemporaryDirectory(prefix="bgrl-replay-") as tmp:
        for fmt, data in policy_files(hf.learner.model, meta).items():
            path = Path(tmp) / f"hf_policy_replay_session{session_id}{SUFFIXES[fmt]}"
            path.write_bytes(data)
            artifact_ids[fmt] = context.store_file(path, kind="model", name=path.name)
    artifact_id = artifact_ids["torchscript"]
    with runtime.sessions() as db:
        relpath = db.scalar(select(Artifact.relpath).where(Artifact.id == artifact_id))
        original = db.get(HFModel, run.hf_model_id) if run.hf_model_id else None
        original_spl = (original.metrics or {}).get("hf_policy_spl") if original else None
    spl = hf_policy_spl(runtime.store.path(str(relpath)), str(run.options.get("task", "sssg")))
    comparison = {
        "decisions": len(decisions),
        "accepted": len(accepted),
        "decisions_compared": len(compared),
        "decisions_agreeing": same,
        "accuracy": hits / known if known else None,
        "original_hf_model_id": run.hf_model_id,
        "original_hf_policy_spl": original_spl,
        "hf_policy_spl": spl,
    }
    with runtime.sessions() as db:
        model = HFModel(
            name=f"session {session_id} pi_HF replayed with classifier {classifier_id} "
            f"({len(labels)} labels)",
            task=str(run.options.get("task", "sssg")),
            feedback_accuracy=comparison["accuracy"],
            n_labels=len(labels),
            session_id=session_id,
            job_id=context.job_id,
            torchscript_artifact_id=artifact_id,
            pt2_artifact_id=artifact_ids["pt2"],
            onnx_artifact_id=artifact_ids["onnx"],
            metrics={
                **metrics,
                "model_version": hf.model_version,
                "hf_policy_spl": spl,
                "replay_of_session": session_id,
                "replay_of_run": run.id,
                "classifier_id": classifier_id,
                "eeg_source": stream.source,
            },
        )
        db.add(model)
        db.commit()
        model_id = model.id
    logger.info("session %s replayed: %d labels, HF model %d", session_id, len(labels), model_id)
    return JobOutcome(
        result={
            "hf_model_id": model_id,
            "session_id": session_id,
            "classifier_id": classifier_id,
            "labels": labels,
            "eeg_source": stream.source,
            "comparison": comparison,
        },
        values={
            "model_artifact_id": artifact_id,
            "model_pt2_artifact_id": artifact_ids["pt2"],
            "model_onnx_artifact_id": artifact_ids["onnx"],
        },
    )
