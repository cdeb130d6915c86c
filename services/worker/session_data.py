"""A stored live session read back: its run's markers and decisions, its labels, and the EEG
the decoder saw, for the BIDS export and the replay jobs (issue 10, "Data a lab keeps").

The EEG of a session comes from, in this order:

* its stored recording (a ``recordings`` row of the session, e.g. the calibration BDF or an
  uploaded file): action onsets are the ``Status`` triggers, matched in order to the run's
  markers that carry an oracle label;
* otherwise, for a run with the virtual subject, the virtual subject's stream regenerated
  from its seed and the run's markers. The subject's samples depend only on its seed, the
  stream's start and the markers, so an accelerated run that was never resumed gets back
  exactly the samples the EEG service decoded live (a resumed run restarted its source, and
  a real-time run started on the wall clock: their stream is regenerated without the break).
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import mne
import numpy as np
from sqlalchemy import select

from services.core.db.live import LiveDecision, LiveMarker, LiveRun
from services.core.db.models import (
    Artifact,
    Classifier,
    FeedbackLabel,
    Job,
    LabSession,
    Recording,
    Subject,
)
from services.core.markers import ActionMarker
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.recordings.io import action_events, is_synthetic, read_recording
from services.eeg.virtual.source import VirtualEEGSource
from services.worker.live_eeg import EPOCH_END_S, WARMUP_S
from services.worker.runtime import JobConfigError, Runtime

CHUNK_S = 0.5
"""Chunk length of the regenerated stream (as the accelerated live driver sends it)."""
TAIL_S = 2.0
"""EEG kept after the last marker's onset."""


@dataclass
class StoredSession:
    """One lab session's rows: its latest live run with markers, decisions and labels."""

    session: LabSession
    subject_code: str
    run: LiveRun | None
    markers: list[LiveMarker] = field(default_factory=list)
    decisions: dict[int, LiveDecision] = field(default_factory=dict)
    labels: dict[int, FeedbackLabel] = field(default_factory=dict)
    recording: Recording | None = None
    recording_relpath: str | None = None


def load_session(runtime: Runtime, session_id: int) -> StoredSession:
    """The rows of lab session ``session_id`` (detached from the database session)."""
    with runtime.sessions() as db:
        lab = db.get(LabSession, session_id)
        if lab is None:
            raise JobConfigError(f"session_id: no session {session_id}")
        subject = db.get(Subject, lab.subject_id)
        runs = db.scalars(
            select(LiveRun).where(LiveRun.session_id == session_id).order_by(LiveRun.id.desc())
        ).all()
        run = None
        markers: list[LiveMarker] = []
        for candidate in runs:
            markers = list(
                db.scalars(
                    select(LiveMarker)
                    .where(LiveMarker.run_id == candidate.id)
                    .order_by(LiveMarker.step)
                )
            )
            if markers:
                run = candidate
                break
        decisions = (
            {
                d.step: d
                for d in db.scalars(select(LiveDecision).where(LiveDecision.run_id == run.id))
            }
            if run is not None
            else {}
        )
        labels = {
            row.step: row
            for row in db.scalars(
                select(FeedbackLabel).where(FeedbackLabel.session_id == session_id)
            )
        }
        row = db.execute(
            select(Recording, Artifact.relpath)
            .join(Artifact, Artifact.id == Recording.artifact_id)
            .where(Recording.session_id == session_id, Recording.validation_status == "valid")
            .order_by(Recording.id.desc())
        ).first()
        db.expunge_all()
    return StoredSession(
        session=lab,
        subject_code=subject.code if subject is not None else str(lab.subject_id),
        run=run,
        markers=markers,
        decisions=decisions,
        labels=labels,
        recording=row[0] if row else None,
        recording_relpath=row[1] if row else None,
    )


def subject_session_ids(runtime: Runtime, subject_id: int) -> list[int]:
    """The subject's lab sessions, oldest first."""
    with runtime.sessions() as db:
        return list(
            db.scalars(
                select(LabSession.id)
                .where(LabSession.subject_id == subject_id)
                .order_by(LabSession.scheduled_at, LabSession.id)
            )
        )


@dataclass
class SessionStream:
    """The EEG of a session as the decoder received it: chunks on the markers' clock."""

    ch_names: list[str]
    sfreq: float
    chunks: Iterator[tuple[np.ndarray, float]]
    """(samples (n_times, n_channels) in volts with Status codes, first timestamp) in order;
    pulled lazily, so markers are fed to a virtual subject before their onset is generated."""
    onsets: dict[int, float]
    """Marker step -> onset on the chunks' clock (markers without one are missing)."""
    start: float
    """Timestamp of the first sample (a file's sample ``i`` is at ``start + i / sfreq``)."""
    synthetic: bool
    description: str
    source: str
    """``recording <id>`` or ``virtual subject (regenerated)``."""
    misc_channels: tuple[str, ...] = ()
    """Channels that are neither EEG nor ``Status`` (a recording's EXG, AUX...)."""


def virtual_source(stored: StoredSession) -> VirtualEEGSource:
    """The run's virtual subject, started where the live runner started it."""
    run = stored.run
    assert run is not None
    options = run.options
    seed = options.get("virtual_seed")
    if seed is None:
        seed = stored.session.subject_id
    # The runner's accelerated source starts at 0 (then warms up WARMUP_S).
    accelerated = options.get("accelerated", False)
    start = 0.0 if accelerated else stored.markers[0].eeg_ts - 1.5 * WARMUP_S
    return VirtualEEGSource(
        quality=float(options.get("virtual_quality", 0.7)), seed=int(seed), start_timestamp=start
    )


def _marker(stored: StoredSession, row: LiveMarker) -> ActionMarker:
    return ActionMarker(
        session_id=row.sim_session_id,
        step=row.sim_step,
        episode=row.episode,
        action=row.action,
        correct=row.oracle_correct,
        timestamp=row.eeg_ts,
    )


def _virtual_chunks(
    stored: StoredSession, source: VirtualEEGSource
) -> Iterator[tuple[np.ndarray, float]]:
    """The regenerated stream: each marker fed just before its onset is generated."""
    pending = list(stored.markers)
    end = stored.markers[-1].eeg_ts + TAIL_S
    while source.next_timestamp < end - 0.5 / source.sfreq:
        horizon = min(end, source.next_timestamp + CHUNK_S)
        while pending and pending[0].eeg_ts < horizon + EPOCH_END_S:
            source.add_marker(_marker(stored, pending.pop(0)))
        samples, first = source.generate_until(horizon)
        if len(samples):
            yield samples, first


def _recording_chunks(raw: mne.io.BaseRaw, chunk: int) -> Iterator[tuple[np.ndarray, float]]:
    for start in range(0, raw.n_times, chunk):
        stop = min(raw.n_times, start + chunk)
        yield raw.get_data(start=start, stop=stop).T, start / raw.info["sfreq"]


def session_stream(runtime: Runtime, stored: StoredSession) -> SessionStream:
    """The EEG of ``stored`` (see the module docstring for where it comes from)."""
    if stored.recording is not None and stored.recording_relpath is not None:
        path = runtime.store.path(stored.recording_relpath)
        raw = read_recording(path)
        sfreq = float(raw.info["sfreq"])
        events = action_events(raw)
        labelled = [m for m in stored.markers if m.oracle_correct is not None]
        onsets: dict[int, float] = {}
        if labelled:
            if len(labelled) != len(events):
                raise JobConfigError(
                    f"recording {stored.recording.id} has {len(events)} action triggers but "
                    f"the session's run has {len(labelled)} labelled markers"
                )
            onsets = {
                m.step: (int(e[0]) - raw.first_samp) / sfreq
                for m, e in zip(labelled, events, strict=True)
            }
        return SessionStream(
            ch_names=list(raw.ch_names),
            sfreq=sfreq,
            chunks=_recording_chunks(raw, max(1, round(CHUNK_S * sfreq))),
            onsets=onsets,
            start=0.0,
            synthetic=is_synthetic(raw),
            description=str(raw.info.get("description") or ""),
            source=f"recording {stored.recording.id}",
            misc_channels=tuple(
                ch for ch, kind in zip(raw.ch_names, raw.get_channel_types(), strict=True)
                if kind == "misc"
            ),
        )  # fmt: skip
    if stored.run is None or not stored.markers:
        raise JobConfigError(f"session {stored.session.id} has neither a recording nor markers")
    if stored.run.options.get("eeg_source", "virtual") != "virtual":
        raise JobConfigError(
            f"session {stored.session.id} ran from a headset and has no stored recording"
        )
    source = virtual_source(stored)
    return SessionStream(
        ch_names=list(source.ch_names),
        sfreq=source.sfreq,
        chunks=_virtual_chunks(stored, source),
        onsets={m.step: m.eeg_ts for m in stored.markers},
        start=source.start_timestamp,
        synthetic=True,
        description=source.description,
        source="virtual subject (regenerated)",
    )


def load_classifier(runtime: Runtime, classifier_id: int) -> ErrPClassifier:
    """The platform classifier ``classifier_id`` loaded from the artifact store."""
    with runtime.sessions() as db:
        classifier = db.get(Classifier, classifier_id)
        if classifier is None:
            raise JobConfigError(f"classifier_id: no classifier {classifier_id}")
        job = db.get(Job, classifier.job_id) if classifier.job_id else None
        files = dict((job.result or {}).get("artifacts", {})) if job is not None else {}
        relpaths = {
            name: db.scalar(select(Artifact.relpath).where(Artifact.id == artifact_id))
            for name, artifact_id in files.items()
            if name.startswith("model") or name == "classifier.json"
        }
    if "classifier.json" not in relpaths:
        raise JobConfigError(f"classifier_id: classifier {classifier_id} has no stored files")
    folder = Path(tempfile.mkdtemp(prefix="bgrl-classifier-"))
    try:
        for name, relpath in relpaths.items():
            if relpath is not None:
                try:
                    shutil.copyfile(runtime.store.path(relpath), folder / name)
                except FileNotFoundError:
                    raise JobConfigError(
                        f"classifier_id: file {name} of classifier {classifier_id} is missing "
                        "from the artifact store"
                    ) from None
        return ErrPClassifier.load(folder)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
