"""SQLite: a consistent snapshot of the live database file, and its restore."""

from __future__ import annotations

import sqlite3
from pathlib import Path

from services.cli.backup.manifest import BackupError, Target, move_into, private_folders


def snapshot_sqlite(path: Path, out: Path) -> None:
    """A consistent copy of the live SQLite database at ``path`` (WAL checkpointed first)."""
    if not path.is_file():
        raise BackupError(f"no SQLite database at {path} (has the platform ever started?)")
    source = sqlite3.connect(f"{path.as_uri()}?mode=rw", uri=True, timeout=30)
    copy = sqlite3.connect(out)
    try:
        # fold the write-ahead log back into the file (PASSIVE: never waits for writers)
        source.execute("PRAGMA wal_checkpoint(PASSIVE)")
        source.backup(copy)
        copy.execute("PRAGMA journal_mode=DELETE")  # one self-contained file
        verdict = copy.execute("PRAGMA integrity_check").fetchone()[0]
        if verdict != "ok":
            raise BackupError(f"the copy of {path} fails SQLite's integrity check: {verdict}")
    finally:
        copy.close()
        source.close()


def place_sqlite(target: Target, staged: Path) -> None:
    """Put the staged database copy in place of ``target``'s SQLite file."""
    path = target.sqlite_path
    private_folders(path.parent)
    for end in ("-wal", "-shm", "-journal"):  # a stale log must not replay onto the copy
        Path(f"{path}{end}").unlink(missing_ok=True)
    move_into(staged, path)
