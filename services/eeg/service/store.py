"""What the EEG service keeps on disk: recordings, classifiers and job records.

Everything lives below ``<data_dir>/eeg``::

    recordings/<sha256>.<bdf|edf|fif>   the validated file
    recordings/<sha256>.json            its RecordingPublic metadata
    classifiers/<job id>/               a trained classifier (ErrPClassifier.save + source.json)
    classifiers/.<job id>.part/         a classifier being trained (removed if the job fails)
    jobs/<job id>.json                  the JobPublic record
    incoming/                           uploads being received or validated

Every file is written under a temporary name and renamed, so a failure never leaves half a
recording, classifier or job record behind.
"""

from __future__ import annotations

import asyncio
import datetime
import json
import logging
import shutil
import threading
from pathlib import Path
from typing import Any

import numpy as np

from services.core.artifacts import ArtifactStore
from services.core.files import private_folder, write_json_atomic
from services.core.web import jsonable
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.recordings.io import (
    RecordingError,
    action_events,
    detect_format,
    file_sha256,
    format_mismatch,
    is_synthetic,
    read_recording,
)
from services.eeg.service.errors import (
    ClassifierNotFoundError,
    ClassifierUnusableError,
    InvalidRecordingError,
    JobNotFoundError,
    RecordingNotFoundError,
    UnsupportedFormatError,
)
from services.eeg.service.schemas import ClassifierPublic, JobPublic, RecordingPublic
from services.eeg.service.uploads import Upload

logger = logging.getLogger(__name__)

SOURCE_FILE = "source.json"
"""File in a classifier folder naming the recording and job it came from."""


def utc_now() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _valid_id(value: str) -> bool:
    return 0 < len(value) <= 64 and value.isascii() and value.isalnum()


def _metadata(
    raw, sha: str, filename: str, fmt: str, size_bytes: int, notes: list[str]
) -> RecordingPublic:
    """What the service stores about a validated recording."""
    events = action_events(raw)
    return RecordingPublic(
        id=sha,
        filename=filename,
        format=fmt,
        sha256=sha,
        size_bytes=size_bytes,
        sfreq=float(raw.info["sfreq"]),
        n_channels=len(raw.ch_names),
        duration_s=raw.n_times / raw.info["sfreq"],
        n_actions=len(events),
        n_errors=int(np.sum(events[:, 2] == 2)),
        synthetic=is_synthetic(raw),
        uploaded_at=utc_now(),
        notes=notes,
    )


class RecordingStore:
    """Validated recordings stored under their sha256."""

    def __init__(self, folder: Path, incoming: ArtifactStore) -> None:
        self.folder = private_folder(folder)  # human EEG: its owner's only
        self.incoming = incoming

    def get(self, recording_id: str) -> RecordingPublic:
        """The metadata of one recording (404 if unknown)."""
        path = self.folder / f"{recording_id}.json"
        if not _valid_id(recording_id) or not path.is_file():
            raise RecordingNotFoundError(f"no recording {recording_id!r}", field="recording_id")
        return RecordingPublic.model_validate_json(path.read_text())

    def list(self) -> list[RecordingPublic]:
        """Every readable stored recording, by id (an unreadable record is logged)."""
        recordings = []
        for path in sorted(self.folder.glob("*.json")):
            try:
                recordings.append(RecordingPublic.model_validate_json(path.read_text()))
            except ValueError as exc:
                logger.warning("skipping unreadable recording record %s: %s", path.name, exc)
        return recordings

    def file(self, recording_id: str) -> Path:
        """The stored file of one recording."""
        meta = self.get(recording_id)
        return self.folder / f"{meta.sha256}.{meta.format}"

    async def add(self, upload: Upload) -> tuple[RecordingPublic, bool]:
        """Validate an upload and keep it; returns its metadata and whether it is new.

        The format is detected from the file's header; a file that is not a usable
        recording is a 415 (not BDF/EDF/FIF) or a 422 (the reason), and is removed.
        """
        tmp = self.incoming.path(upload.stored.relpath)
        try:
            return await asyncio.to_thread(self._validate_and_keep, tmp, upload)
        finally:
            self.incoming.delete(upload.stored.relpath)

    def _validate_and_keep(self, tmp: Path, upload: Upload) -> tuple[RecordingPublic, bool]:
        shown = Path(upload.filename).name if upload.filename else "upload"
        sha = upload.stored.sha256
        existing = self.folder / f"{sha}.json"
        if existing.is_file():
            return RecordingPublic.model_validate_json(existing.read_text()), False
        try:
            fmt = detect_format(tmp, name=shown)
        except RecordingError as exc:
            raise UnsupportedFormatError(str(exc), field="file") from None
        named = tmp.with_name(f"{tmp.name}.{fmt}")
        tmp.replace(named)
        try:
            try:
                raw = read_recording(named, name=shown)
            except RecordingError as exc:
                raise InvalidRecordingError(str(exc), field="file") from None
            note = format_mismatch(shown, fmt)
            meta = _metadata(raw, sha, shown, fmt, upload.stored.size_bytes, [note] if note else [])
            del raw
            named.replace(self.folder / f"{sha}.{fmt}")
        finally:
            named.unlink(missing_ok=True)
        write_json_atomic(existing, meta.model_dump())
        logger.info("stored recording %s (%s, %s)", sha[:12], fmt, shown)
        return meta, True

    def add_bdf(
        self,
        path: Path,
        *,
        filename: str,
        ch_names: list[str],
        notes: list[str],
        sha256: str | None = None,
    ) -> RecordingPublic:
        """Validate a BDF the service wrote (a live recording) and keep it under its sha256
        (``sha256`` if the caller has hashed the file, else hashed here).

        ``ch_names`` are the EEG channels it must hold. The file is moved into the store; a
        file that is not a usable recording is a 422 naming the reason and stays where it is.
        """
        sha = sha256 or file_sha256(path)
        existing = self.folder / f"{sha}.json"
        if existing.is_file():
            path.unlink()
            return RecordingPublic.model_validate_json(existing.read_text())
        try:
            raw = read_recording(path, name=filename, ch_names=ch_names)
        except RecordingError as exc:
            raise InvalidRecordingError(str(exc), field="name") from None
        meta = _metadata(raw, sha, filename, "bdf", path.stat().st_size, notes)
        del raw
        path.replace(self.folder / f"{sha}.bdf")
        write_json_atomic(existing, meta.model_dump())
        logger.info("stored recording %s (live recording %s)", sha[:12], filename)
        return meta


class ClassifierStore:
    """Trained classifiers, loaded once and cached (thread-safe)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._cache: dict[str, ErrPClassifier] = {}

    def staging(self, job_id: str) -> Path:
        """Folder where job ``job_id`` writes its classifier until it succeeds."""
        return self.folder / f".{job_id}.part"

    def publish(self, job_id: str, recording_id: str) -> str:
        """Move a job's staged classifier into place; returns the classifier id."""
        staging = self.staging(job_id)
        write_json_atomic(staging / SOURCE_FILE, {"recording_id": recording_id, "job": job_id})
        staging.replace(self.folder / job_id)
        return job_id

    def discard(self, job_id: str) -> None:
        """Remove what a failed or cancelled job staged."""
        shutil.rmtree(self.staging(job_id), ignore_errors=True)

    def get(self, classifier_id: str) -> ErrPClassifier:
        """The classifier (404 if unknown, 409 if its files cannot be loaded)."""
        folder = self.folder / classifier_id
        if not _valid_id(classifier_id) or not folder.is_dir():
            raise ClassifierNotFoundError(f"no classifier {classifier_id!r}", field="classifier_id")
        with self._lock:
            if classifier_id not in self._cache:
                try:
                    self._cache[classifier_id] = ErrPClassifier.load(folder)
                except (ValueError, OSError, KeyError) as exc:
                    logger.warning("classifier %s cannot be loaded: %s", classifier_id, exc)
                    raise ClassifierUnusableError(
                        f"classifier {classifier_id!r} cannot be loaded "
                        f"({type(exc).__name__}: {str(exc).replace(str(folder), classifier_id)})",
                        field="classifier_id",
                    ) from None
            return self._cache[classifier_id]

    def public(self, classifier_id: str) -> ClassifierPublic:
        """What the API shows of one classifier."""
        clf = self.get(classifier_id)
        source = self.folder / classifier_id / SOURCE_FILE
        recording_id = None
        if source.is_file():
            try:
                recording_id = str(json.loads(source.read_text())["recording_id"])
            except (ValueError, KeyError, TypeError) as exc:
                logger.warning("classifier %s: unreadable %s: %s", classifier_id, SOURCE_FILE, exc)
        return ClassifierPublic(
            id=classifier_id,
            recording_id=recording_id,
            synthetic=clf.synthetic,
            ch_names=clf.ch_names,
            sfreq_in=clf.sfreq_in,
            epoch_shape=clf.epoch_shape,
            metrics=jsonable(clf.metrics),
        )

    def list(self) -> list[ClassifierPublic]:
        """Every usable classifier; one whose files cannot be loaded is left out (logged;
        ``GET /classifiers/{id}`` answers 409 with the reason)."""
        usable = []
        for classifier_id in self.ids():
            try:
                usable.append(self.public(classifier_id))
            except ClassifierUnusableError:
                continue
        return usable

    def ids(self) -> list[str]:
        """Ids of every trained classifier."""
        return sorted(
            p.name for p in self.folder.iterdir() if p.is_dir() and not p.name.startswith(".")
        )


class JobStore:
    """Job records (one JSON file each); updates are serialised by one lock."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.lock = threading.RLock()
        """Held while a job's status is read and changed, so transitions never interleave."""

    def get(self, job_id: str) -> JobPublic:
        """One job record (404 if unknown)."""
        path = self.folder / f"{job_id}.json"
        if not _valid_id(job_id) or not path.is_file():
            raise JobNotFoundError(f"no job {job_id!r}", field="job_id")
        return JobPublic.model_validate_json(path.read_text())

    def list(self) -> list[JobPublic]:
        """Every readable job record, oldest first (an unreadable one is logged)."""
        jobs = []
        for path in self.folder.glob("*.json"):
            try:
                jobs.append(JobPublic.model_validate_json(path.read_text()))
            except ValueError as exc:
                logger.warning("skipping unreadable job record %s: %s", path.name, exc)
        return sorted(jobs, key=lambda job: job.created_at)

    def save(self, job: JobPublic) -> JobPublic:
        """Write a job record (atomically) and return it."""
        write_json_atomic(self.folder / f"{job.id}.json", job.model_dump())
        return job

    def update(self, job_id: str, **changes: Any) -> JobPublic:
        """Change fields of a stored job record."""
        with self.lock:
            return self.save(self.get(job_id).model_copy(update=changes))
