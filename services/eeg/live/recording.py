"""Live recording: the live EEG stream and every action marker, written to disk as they come.

A recording in progress is a folder (``<data_dir>/eeg/live_recordings/<name>/``)::

    samples.f32    every sample received, float32, time-major (n_times x n_channels)
    index.jsonl    one JSON object per line: the header, then "run" lines (which samples
                   were flushed, with the timestamps of their first and last sample) and
                   "marker" lines (each action marker received, with its Status code)
    stored.json    {"sha256": ...} of the finalised BDF, written just before the EEG service
                   stores it; the folder is removed after (this file last), so a folder
                   still holding it after a crash is known to be stored if the store has
                   that sha256

Samples are buffered and appended in blocks of ``block_s`` of stream time; the samples are
written before the index lines that describe them, so after a crash the index names only
complete data, and :func:`read_log` recovers everything up to the last flushed block (a
half-written last line of the index and samples no index line names are ignored).

:func:`write_bdf_from_log` finalises a folder into a 24-bit BDF: the stream's channels in
microvolts and a ``Status`` channel written as the virtual subject writes it (a 10 ms pulse of
1 for a correct action, 2 for an error, at the sample of the marker's timestamp; markers
without an oracle label leave no pulse). A ``Status`` channel of the stream itself is replaced
by the markers' codes. The BDF is synthetic when the source said so.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
import os
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mne
import numpy as np

from services.core.markers import ActionMarker
from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_TAG, TRIGGER_PULSE_S
from services.eeg.recordings.io import write_bdf

logger = logging.getLogger(__name__)

SAMPLES_FILE = "samples.f32"
INDEX_FILE = "index.jsonl"
STORED_FILE = "stored.json"
FSYNC_EVERY_S = 5.0
"""Wall-clock period of fsync (a flushed block survives a crash of the service at once, a
crash of the machine once synced)."""
GAP_TOLERANCE_SAMPLES = 1.5
"""A timestamp step off the nominal period by more than this starts a new run."""


class RecordingLogError(ValueError):
    """A recording folder cannot be read or does not match the stream."""


@dataclass
class Run:
    """Consecutive samples without a gap: samples ``start:start + n`` of the file."""

    start: int
    n: int
    first_timestamp: float
    last_timestamp: float


@dataclass
class RecordingLog:
    """What a recording folder holds (complete data only)."""

    folder: Path
    name: str
    ch_names: list[str]
    sfreq: float
    synthetic: bool
    description: str
    started_at: str
    runs: list[Run] = field(default_factory=list)
    markers: list[dict[str, Any]] = field(default_factory=list)

    @property
    def n_samples(self) -> int:
        return sum(run.n for run in self.runs)

    def samples(self) -> np.ndarray:
        """The flushed samples (a read-only memory map, n_times x n_channels)."""
        n = self.n_samples
        if n == 0:
            return np.zeros((0, len(self.ch_names)), dtype=np.float32)
        return np.memmap(
            self.folder / SAMPLES_FILE, dtype="<f4", mode="r", shape=(n, len(self.ch_names))
        )

    def marker_samples(self) -> tuple[list[tuple[int, int]], int]:
        """``(sample, code)`` of every marker inside a run, and how many fell outside."""
        half = 0.5 / self.sfreq
        placed, outside = [], 0
        for marker in self.markers:
            ts = marker["timestamp"]
            run = next(
                (r for r in self.runs if r.first_timestamp - half <= ts <= r.last_timestamp + half),
                None,
            )
            if run is None:
                outside += 1
                continue
            offset = min(max(round((ts - run.first_timestamp) * self.sfreq), 0), run.n - 1)
            placed.append((run.start + offset, int(marker["trigger"])))
        return placed, outside


def _json_line(payload: dict[str, Any]) -> bytes:
    return (json.dumps(payload, allow_nan=False) + "\n").encode()


def read_log(folder: Path) -> RecordingLog:
    """Recover a recording folder: everything up to the last flushed block.

    Raises :class:`RecordingLogError` when the folder has no readable header.
    """
    index = folder / INDEX_FILE
    if not index.is_file():
        raise RecordingLogError(f"{folder.name}: no {INDEX_FILE}")
    lines = index.read_bytes().split(b"\n")
    entries = []
    for number, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            entries.append(json.loads(line))
        except json.JSONDecodeError:
            if number == len(lines) - 1:  # the line being written when the writer stopped
                break
            raise RecordingLogError(f"{folder.name}: line {number + 1} is not JSON") from None
    if not entries or entries[0].get("kind") != "header":
        raise RecordingLogError(f"{folder.name}: the index has no header")
    head = entries[0]
    log = RecordingLog(
        folder=folder,
        name=head["name"],
        ch_names=list(head["ch_names"]),
        sfreq=float(head["sfreq"]),
        synthetic=bool(head["synthetic"]),
        description=head.get("description", ""),
        started_at=head["started_at"],
    )
    tolerance = GAP_TOLERANCE_SAMPLES / log.sfreq
    for entry in entries[1:]:
        if entry.get("kind") == "run":
            run = Run(entry["start"], entry["n"], entry["first_timestamp"], entry["last_timestamp"])
            last = log.runs[-1] if log.runs else None
            if (
                last is not None
                and run.start == last.start + last.n
                and abs(run.first_timestamp - last.last_timestamp - 1 / log.sfreq) <= tolerance
            ):
                last.n += run.n
                last.last_timestamp = run.last_timestamp
            else:
                log.runs.append(run)
        elif entry.get("kind") == "marker":
            log.markers.append(entry)
    size = (folder / SAMPLES_FILE).stat().st_size if (folder / SAMPLES_FILE).is_file() else 0
    if size < log.n_samples * len(log.ch_names) * 4:
        raise RecordingLogError(f"{folder.name}: {SAMPLES_FILE} is shorter than its index says")
    return log


class LiveRecorder:
    """Appends a live stream's samples and markers to a recording folder.

    Opening a folder that already holds a recording of the same channels and rate (a
    recording interrupted by a crash) continues it; the index then shows the gap.

    Parameters
    ----------
    folder : Path
        The recording's folder (created if needed).
    name : str
        The recording's name (the stored BDF is ``<name>.bdf``).
    ch_names : sequence of str
        The stream's channels, in column order.
    sfreq : float
        The stream's nominal rate (Hz).
    synthetic : bool
        The source says its data are generated.
    block_s : float
        Stream time buffered before each append.
    """

    def __init__(
        self,
        folder: Path,
        *,
        name: str,
        ch_names: Sequence[str],
        sfreq: float,
        synthetic: bool,
        block_s: float = 1.0,
    ) -> None:
        self.folder = folder
        self.name = name
        self.ch_names = list(ch_names)
        self.sfreq = float(sfreq)
        self.synthetic = synthetic
        self._block = max(1, round(block_s * self.sfreq))
        self._lock = threading.Lock()
        self._buffer: list[np.ndarray] = []
        self._buffered = 0
        self._pending_runs: list[Run] = []
        self._pending_markers: list[dict[str, Any]] = []
        self._run: Run | None = None
        self._last_sync = time.monotonic()
        self.error: str | None = None
        """Why recording stopped taking data (e.g. a disk error), if it did."""
        self.resumed = (folder / INDEX_FILE).is_file()
        if self.resumed:
            log = read_log(folder)
            if log.ch_names != self.ch_names or not math.isclose(log.sfreq, self.sfreq):
                raise RecordingLogError(
                    f"recording {name!r} exists with other channels or rate "
                    f"({len(log.ch_names)} channels at {log.sfreq:g} Hz)"
                )
            self.started_at = log.started_at
            self.n_samples = log.n_samples
            self.n_markers = len(log.markers)
            self.synthetic = log.synthetic
            with (folder / SAMPLES_FILE).open("r+b") as fh:  # drop unindexed bytes
                fh.truncate(self.n_samples * len(self.ch_names) * 4)
            self._truncate_index_tail()
        else:
            folder.mkdir(parents=True, exist_ok=True)
            self.started_at = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
            self.n_samples = 0
            self.n_markers = 0
            (folder / SAMPLES_FILE).write_bytes(b"")
            description = (
                f"{SYNTHETIC_TAG} live recording {name} of a virtual subject"
                if synthetic
                else f"live recording {name}"
            )
            header = {
                "kind": "header",
                "name": name,
                "ch_names": self.ch_names,
                "sfreq": self.sfreq,
                "synthetic": synthetic,
                "description": description,
                "started_at": self.started_at,
            }
            (folder / INDEX_FILE).write_bytes(_json_line(header))
        self._samples_fh = (folder / SAMPLES_FILE).open("ab")
        self._index_fh = (folder / INDEX_FILE).open("ab")

    def _truncate_index_tail(self) -> None:
        """Cut a half-written last index line (left by a crash) before appending."""
        path = self.folder / INDEX_FILE
        data = path.read_bytes()
        if data and not data.endswith(b"\n"):
            with path.open("r+b") as fh:
                fh.truncate(data.rfind(b"\n") + 1)

    # ------------------------------------------------------------------ input
    def add_samples(self, samples: np.ndarray, timestamps: np.ndarray) -> None:
        """Buffer one chunk (n_times x n_channels) with its per-sample timestamps."""
        if self.error is not None or len(samples) == 0:
            return
        with self._lock:
            try:
                period = 1.0 / self.sfreq
                steps = np.abs(np.diff(timestamps) - period) > GAP_TOLERANCE_SAMPLES * period
                cuts = np.flatnonzero(steps) + 1
                for lo, hi in zip(np.r_[0, cuts], np.r_[cuts, len(timestamps)], strict=True):
                    self._extend_run(float(timestamps[lo]), float(timestamps[hi - 1]), int(hi - lo))
                    self._buffered += int(hi - lo)
                self._buffer.append(np.asarray(samples, dtype="<f4"))
                if self._buffered >= self._block:
                    self._flush()
            except Exception as exc:  # never break the live ingest: report it instead
                self._fail(exc)

    def _extend_run(self, first: float, last: float, n: int) -> None:
        """Account ``n`` samples about to be buffered: they extend the open run or start one."""
        run = self._run
        period = 1.0 / self.sfreq
        if run is not None and abs(first - run.last_timestamp - period) <= (
            GAP_TOLERANCE_SAMPLES * period
        ):
            run.n += n
            run.last_timestamp = last
            return
        self._run = Run(self.n_samples + self._buffered, n, first, last)
        self._pending_runs.append(self._run)

    def add_marker(self, marker: ActionMarker) -> None:
        """Record an action marker (written with the next block)."""
        with self._lock:
            self.n_markers += 1
            self._pending_markers.append(
                {"kind": "marker", **marker.model_dump(mode="json"), "trigger": marker.trigger}
            )

    # ----------------------------------------------------------------- output
    def _flush(self) -> None:
        """Append the buffered samples, then the index lines describing them."""
        if self._buffer:
            data = np.concatenate(self._buffer)
            self._samples_fh.write(np.ascontiguousarray(data).tobytes())
            self._samples_fh.flush()
        lines = []
        # Runs: every run touched since the last flush, as far as it is flushed now.
        for run in self._pending_runs:
            lines.append(
                {
                    "kind": "run",
                    "start": run.start,
                    "n": run.n,
                    "first_timestamp": run.first_timestamp,
                    "last_timestamp": run.last_timestamp,
                }
            )
        lines.extend(self._pending_markers)
        self._index_fh.write(b"".join(_json_line(line) for line in lines))
        self._index_fh.flush()
        if time.monotonic() - self._last_sync > FSYNC_EVERY_S:
            os.fsync(self._samples_fh.fileno())
            os.fsync(self._index_fh.fileno())
            self._last_sync = time.monotonic()
        self.n_samples += self._buffered
        self._buffer, self._buffered = [], 0
        self._pending_markers, self._pending_runs = [], []
        # A run going on continues as a new run line (read_log merges contiguous lines).
        self._run = None

    def _fail(self, exc: BaseException) -> None:
        self.error = f"recording {self.name!r} stopped: {type(exc).__name__}: {exc}"
        logger.error(self.error)

    def flush(self) -> None:
        """Write everything buffered now."""
        with self._lock:
            try:
                self._flush()
            except Exception as exc:
                self._fail(exc)

    def close(self) -> None:
        """Flush and close the files (the folder stays, ready to finalise or continue)."""
        self.flush()
        with self._lock:
            self._samples_fh.close()
            self._index_fh.close()

    def duration_s(self) -> float:
        return (self.n_samples + self._buffered) / self.sfreq


class _LogRecording:
    """A recording folder as :func:`services.eeg.recordings.io.write_bdf` reads a generated
    recording."""

    def __init__(self, log: RecordingLog) -> None:
        self._log = log
        stream_eeg = [k for k, ch in enumerate(log.ch_names) if ch != STIM_CHANNEL]
        self._eeg = np.array(stream_eeg)
        names = [log.ch_names[k] for k in stream_eeg]
        self.info = mne.create_info(
            [*names, STIM_CHANNEL], log.sfreq, [*["eeg"] * len(names), "stim"]
        )
        self.info["description"] = log.description
        # The header's start is the recording's: finalising the same folder again (after a
        # crash) writes the same bytes, hence the same sha256, on any day.
        self.info.set_meas_date(datetime.datetime.fromisoformat(log.started_at))
        self.n_times = log.n_samples
        status = np.zeros(self.n_times, dtype=np.float32)
        pulse = max(1, round(TRIGGER_PULSE_S * log.sfreq))
        placed, self.outside = log.marker_samples()
        for sample, code in placed:
            if code:
                status[sample : sample + pulse] = code
        self._status = status
        self.placed = placed

    def iter_chunks(self, block: int = 1 << 16) -> Iterator[tuple[int, np.ndarray]]:
        samples = self._log.samples()
        for start in range(0, self.n_times, block):
            stop = min(start + block, self.n_times)
            out = np.empty((len(self._eeg) + 1, stop - start), dtype=np.float32)
            out[:-1] = samples[start:stop, self._eeg].T
            out[-1] = self._status[start:stop]
            yield start, out


@dataclass(frozen=True)
class FinalisedRecording:
    """A BDF written from a recording folder."""

    path: Path
    n_markers: int
    markers_outside: int
    n_runs: int


def write_bdf_from_log(log: RecordingLog, path: Path) -> FinalisedRecording:
    """Write a recording folder's complete data as a BDF (see the module docstring)."""
    if log.n_samples == 0:
        raise RecordingLogError(f"recording {log.name!r} holds no samples")
    recording = _LogRecording(log)
    write_bdf(recording, path)  # type: ignore[arg-type]  # duck-typed like SyntheticRecording
    return FinalisedRecording(path, len(log.markers), recording.outside, len(log.runs))
