"""The journal of an HF session: every change of its state since its last checkpoint.

``<id>/journal.jsonl`` holds one JSON line per operation that changes the session: a new
label (``{"seq", "op": "label", "marker_id", "observation", "action", "correct",
"p_error", "oracle_correct"}``) or a sampled action (``{"seq", "op": "act",
"observation"}``). ``seq`` is the session's operation count after the operation
(:attr:`HFSession.ops <services.learner.service.session.HFSession.ops>`), and ``state.pt``
records the count it was written at, so a restart replays exactly the entries the
checkpoint lacks.

An entry is handed to the kernel (one ``write`` on a file opened for appending) before the
request that made it is answered, which a crash of the service process cannot undo; it is
synced to the disk right after the answer. Replaying a label reruns its Fhat update, which is
deterministic, so the replayed session is bit for bit the one that answered.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

JOURNAL_FILE = "journal.jsonl"


class SessionJournal:
    """An append-only file of JSON lines, synced on demand and emptied after a checkpoint."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self._unsynced = False

    def append(self, entry: dict[str, Any]) -> None:
        """Add one entry (one ``write``, not yet synced)."""
        line = (json.dumps(entry, allow_nan=False, separators=(",", ":")) + "\n").encode()
        written = os.write(self._fd, line)
        if written != len(line):  # a regular file writes all or raises, short of a full disk
            raise OSError(f"journal {self.path}: {written} of {len(line)} bytes written")
        self._unsynced = True

    def sync(self) -> None:
        """Make the entries written so far durable (``fsync``)."""
        if self._unsynced:
            os.fsync(self._fd)
            self._unsynced = False

    def clear(self) -> None:
        """Empty the journal (its entries are in a checkpoint written before)."""
        os.ftruncate(self._fd, 0)
        os.fsync(self._fd)
        self._unsynced = False

    def close(self) -> None:
        """Sync and close the file (closed even if the sync fails)."""
        try:
            self.sync()
        finally:
            os.close(self._fd)


def read_journal(path: Path) -> list[dict[str, Any]]:
    """The entries of a journal file (none if it does not exist).

    A last line without its newline, or that does not parse, is an entry cut by a crash
    while it was written (so never answered) and is dropped; a bad line before the last is
    a damaged file and raises ValueError.
    """
    if not path.exists():
        return []
    lines = path.read_bytes().split(b"\n")
    entries = []
    for number, line in enumerate(lines[:-1], start=1):
        try:
            entries.append(json.loads(line))
        except ValueError as exc:
            if number == len(lines) - 1:  # the last line: cut when it was synced
                break
            raise ValueError(f"journal {path} line {number} is damaged: {exc}") from exc
    return entries
