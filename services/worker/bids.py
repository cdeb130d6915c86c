"""BIDS export of a subject's sessions (mne-bids): ``bids_export`` jobs and ``bgrl bids export``.

Each session with EEG (see :mod:`services.worker.session_data`) becomes
``sub-<code>/ses-<session id>/eeg/sub-<code>_ses-<id>_task-<kind>_eeg.bdf`` with its sidecars
(``_eeg.json``, ``_channels.tsv``, ``_events.tsv`` + ``_events.json``). Every executed action
is an event: ``trial_type`` is ``<action>/<oracle label>`` (``forward/correct``,
``turn_left/error``...) and extra columns give the step, the action index, the oracle label,
the live decision (``ok``/``rejected``), the decoded feedback and its probability. The
synthetic flag of generated data is in ``participants.tsv`` (``synthetic``), in each
``_eeg.json`` (``SyntheticData``) and in ``dataset_description.json`` (``GeneratedBy``).
"""

from __future__ import annotations

import csv
import json
import logging
import re
import shutil
import tempfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mne
import mne_bids
import numpy as np
from sqlalchemy import select

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR, Action
from services.core.db.models import Subject
from services.eeg.recordings.bdf import write_bdf
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.io import action_events, detect_format
from services.eeg.virtual.subject import LINE_FREQ_HZ
from services.platform.jobs import BIDS_EXPORT
from services.worker.runtime import JobConfigError, JobContext, JobOutcome, Runtime, parse_config
from services.worker.session_data import (
    SessionStream,
    StoredSession,
    load_session,
    session_stream,
    subject_session_ids,
)

logger = logging.getLogger(__name__)

LABELS = {True: "correct", False: "error", None: "unlabelled"}
ACTION_EVENT_ID = {
    f"{action.name.lower()}/{label}": 10 * (int(action) + 1) + code
    for action in Action
    for code, label in enumerate(("unlabelled", "correct", "error"))
}
"""``trial_type`` -> event value of an executed action (tens: action + 1; units: label)."""
TRIGGER_EVENT_ID = {"correct": TRIGGER_CORRECT, "error": TRIGGER_ERROR}
"""Events of a recording whose session has no live run (Status triggers only)."""
EXTRA_COLUMNS = {
    "step": "Action index in the live run (0-based).",
    "action": "Action executed: 0 forward 0.3 m, 1 turn left 30 deg, 2 turn right 30 deg.",
    "oracle_label": "The oracle's label of the action: correct, error or n/a.",
    "decision": "The live decoder's decision on the epoch: ok, rejected or n/a (not decoded).",
    "decoded_feedback": "Feedback decoded live from the EEG: correct, error or n/a.",
    "p_error": "The classifier's probability that the action was an error (n/a if none).",
}


@dataclass
class ExportedSession:
    """What one session contributed to the dataset."""

    session_id: int
    task: str
    events: int
    synthetic: bool
    source: str
    path: str


def bids_label(text: str) -> str:
    """A BIDS entity label (alphanumeric) for a subject code or a name."""
    label = re.sub(r"[^A-Za-z0-9]", "", text)
    if not label:
        raise ValueError(f"{text!r} has no letters or digits to make a BIDS label of")
    return label


def _is_bdf(path: Path) -> bool:
    """A BDF file named ``.bdf`` (mne-bids copies it as it is); recordings of every other
    format the platform reads (EDF, FIF, BrainVision and EEGLAB zips, XDF), and a BDF under
    another name, are read by the EEG pipeline and written as BDF."""
    return path.suffix.lower() == ".bdf" and detect_format(path) == "bdf"


def _raw_for(stream: SessionStream, folder: Path, name: str) -> mne.io.BaseRaw:
    """The session's EEG as a BDF read back (the file mne-bids copies into the dataset)."""
    data = np.concatenate([chunk for chunk, _ in stream.chunks]).T.astype(np.float64)
    types = ["stim" if ch == STIM_CHANNEL else "eeg" for ch in stream.ch_names]
    info = mne.create_info(stream.ch_names, stream.sfreq, types)
    raw = mne.io.RawArray(data, info, verbose="error")
    raw.info["description"] = stream.description
    path = write_bdf(raw, folder / f"{name}.bdf")
    return mne.io.read_raw_bdf(path, stim_channel=STIM_CHANNEL, verbose="error")


def _events(
    stored: StoredSession, stream: SessionStream, raw: mne.io.BaseRaw
) -> tuple[np.ndarray, dict[str, int], list[dict[str, Any]]]:
    """MNE events, their event_id and the extra columns (one row per event)."""
    sfreq = raw.info["sfreq"]
    if stored.markers:
        rows, events = [], []
        for marker in stored.markers:
            onset = stream.onsets.get(marker.step)
            if onset is None:
                continue
            label = LABELS[marker.oracle_correct]
            trial_type = f"{Action(marker.action).name.lower()}/{label}"
            sample = round((onset - stream.start) * sfreq) + raw.first_samp
            events.append([sample, 0, ACTION_EVENT_ID[trial_type]])
            decision = stored.decisions.get(marker.step)
            rows.append(
                {
                    "step": marker.step,
                    "action": marker.action,
                    "oracle_label": label if marker.oracle_correct is not None else "n/a",
                    "decision": decision.status if decision else "n/a",
                    "decoded_feedback": (decision.feedback if decision else None) or "n/a",
                    "p_error": "n/a"
                    if decision is None or decision.p_error is None
                    else f"{decision.p_error:.6f}",
                }
            )
        return np.array(events, dtype=int).reshape(-1, 3), ACTION_EVENT_ID, rows
    events = action_events(raw)
    return events, TRIGGER_EVENT_ID, []


def _append_columns(events_tsv: Path, rows: list[dict[str, Any]]) -> None:
    """Add the extra columns to ``_events.tsv`` (rows in onset order, as the events) and
    describe them in ``_events.json``."""
    with events_tsv.open(newline="") as handle:
        table = list(csv.DictReader(handle, delimiter="\t"))
    if len(table) != len(rows):
        raise RuntimeError(f"{events_tsv.name}: {len(table)} events written, {len(rows)} expected")
    fields = [*table[0].keys(), *EXTRA_COLUMNS] if table else list(EXTRA_COLUMNS)
    with events_tsv.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, delimiter="\t", lineterminator="\n")
        writer.writeheader()
        for row, extra in zip(table, rows, strict=True):
            writer.writerow({**row, **{k: str(v) for k, v in extra.items()}})
    sidecar = events_tsv.with_suffix(".json")
    described = json.loads(sidecar.read_text()) if sidecar.exists() else {}
    described.update({name: {"Description": text} for name, text in EXTRA_COLUMNS.items()})
    sidecar.write_text(json.dumps(described, indent=2) + "\n")


def _export_session(
    runtime: Runtime, root: Path, subject: str, session_id: int, scratch: Path
) -> ExportedSession:
    stored = load_session(runtime, session_id)
    stream = session_stream(runtime, stored)
    task = bids_label(stored.session.kind)
    path = runtime.store.path(stored.recording_relpath) if stored.recording_relpath else None
    if stored.recording is not None and path is not None and _is_bdf(path):
        raw = mne.io.read_raw_bdf(path, stim_channel=STIM_CHANNEL, verbose="error")
    else:  # the virtual subject's stream, or a recording of another format: written as BDF
        raw = _raw_for(stream, scratch, f"session-{session_id}")
    misc = [ch for ch in stream.misc_channels if ch in raw.ch_names]
    if misc:  # a BDF types every channel but Status as EEG: channels.tsv says MISC for these
        raw.set_channel_types(dict.fromkeys(misc, "misc"), verbose="error")
    if stream.synthetic:
        raw.info["line_freq"] = LINE_FREQ_HZ
    events, event_id, rows = _events(stored, stream, raw)
    bids_path = mne_bids.BIDSPath(
        subject=subject, session=str(session_id), task=task, datatype="eeg", root=root
    )
    mne_bids.write_raw_bids(
        raw,
        bids_path,
        events=events if len(events) else None,
        event_id=event_id if len(events) else None,
        overwrite=True,
        verbose="error",
    )
    if rows:
        _append_columns(bids_path.copy().update(suffix="events", extension=".tsv").fpath, rows)
    sidecar = bids_path.copy().update(suffix="eeg", extension=".json")
    mne_bids.update_sidecar_json(
        sidecar,
        {
            "SyntheticData": stream.synthetic,
            "TaskDescription": f"bgrl {stored.session.kind} session {session_id}: the subject "
            "watches the robot act (one action per period) and its EEG is decoded for ErrPs.",
        },
        verbose="error",
    )
    return ExportedSession(
        session_id=session_id,
        task=task,
        events=len(events),
        synthetic=stream.synthetic,
        source=stream.source,
        path=str(bids_path.fpath.relative_to(root)),
    )


def _write_participant_flag(root: Path, subject: str, synthetic: bool) -> None:
    path = root / "participants.tsv"
    with path.open(newline="") as handle:
        table = list(csv.DictReader(handle, delimiter="\t"))
    fields = [*table[0].keys()] if table else ["participant_id"]
    if "synthetic" not in fields:
        fields.append("synthetic")
    for row in table:
        if row["participant_id"] == f"sub-{subject}":
            row["synthetic"] = "true" if synthetic else "false"
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields, delimiter="\t", lineterminator="\n")
        writer.writeheader()
        writer.writerows(table)
    sidecar = root / "participants.json"
    described = json.loads(sidecar.read_text()) if sidecar.exists() else {}
    described["synthetic"] = {
        "Description": "true: the EEG was generated by the platform's virtual subject.",
        "Levels": {"true": "generated (synthetic)", "false": "recorded from a person"},
    }
    sidecar.write_text(json.dumps(described, indent=2) + "\n")


def export_subject(
    runtime: Runtime,
    subject_id: int,
    out_dir: Path,
    before_session: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Write the BIDS dataset of subject ``subject_id`` into ``out_dir`` (created; must be
    empty or absent). Sessions without EEG are listed as skipped, with the reason.

    ``before_session(done, total)`` is called before each session is exported (a job
    reports its progress and stops there if cancelled)."""
    with runtime.sessions() as db:
        subject = db.get(Subject, subject_id)
        if subject is None:
            raise JobConfigError(f"subject_id: no subject {subject_id}")
        code = subject.code
    if out_dir.exists() and any(out_dir.iterdir()):
        raise JobConfigError(f"out: {out_dir} is not empty")
    out_dir.mkdir(parents=True, exist_ok=True)
    label = bids_label(code)
    exported: list[ExportedSession] = []
    skipped: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bgrl-bids-") as scratch:
        session_ids = subject_session_ids(runtime, subject_id)
        for done, session_id in enumerate(session_ids):
            if before_session is not None:
                before_session(done, len(session_ids))
            try:
                exported.append(_export_session(runtime, out_dir, label, session_id, Path(scratch)))
            except JobConfigError as exc:
                skipped.append({"session_id": session_id, "reason": str(exc)})
    if not exported:
        raise JobConfigError(f"subject {code} has no session with EEG to export")
    synthetic = any(s.synthetic for s in exported)
    _write_participant_flag(out_dir, label, synthetic)
    kind = "synthetic (the platform's virtual subject)" if synthetic else "recorded"
    mne_bids.make_dataset_description(
        path=out_dir,
        name=f"brain-guided-rl subject {code}",
        dataset_type="raw",
        generated_by=[
            {
                "Name": "brain-guided-rl",
                "Description": f"bgrl BIDS export; EEG {kind}",
            }
        ],
        overwrite=True,
        verbose="error",
    )
    return {
        "subject": code,
        "bids_subject": label,
        "synthetic": synthetic,
        "sessions": [vars(s) for s in exported],
        "skipped": skipped,
    }


def zip_folder(folder: Path, target: Path) -> Path:
    """``folder``'s files in a zip (paths relative to it)."""
    with zipfile.ZipFile(target, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                archive.write(path, path.relative_to(folder).as_posix())
    return target


def bids_export(context: JobContext) -> JobOutcome:
    """Handler of ``bids_export`` jobs: config ``{subject_id}``; the zip is a ``bids``
    artifact."""
    subject_id = parse_config(BIDS_EXPORT, context.config).subject_id
    with tempfile.TemporaryDirectory(prefix="bgrl-bids-job-") as tmp:
        root = Path(tmp) / "bids"

        def before_session(done: int, total: int) -> None:
            context.check_stop()
            context.update(progress=0.9 * done / total)

        summary = export_subject(context.runtime, subject_id, root, before_session)
        context.check_stop()
        archive = zip_folder(root, Path(tmp) / f"bids-sub-{summary['bids_subject']}.zip")
        artifact_id = context.store_file(archive, kind="bids", name=archive.name)
        shutil.rmtree(root, ignore_errors=True)
    return JobOutcome(result={**summary, "artifact_id": artifact_id})


def subject_id_for_code(runtime: Runtime, code: str) -> int:
    """The id of the subject with this code (``bgrl bids export --subject CODE``)."""
    with runtime.sessions() as db:
        found = db.scalar(select(Subject.id).where(Subject.code == code))
    if found is None:
        raise JobConfigError(f"subject: no subject with code {code!r}")
    return int(found)
