"""Atomic file writes: a reader sees the old file or the new one, never half of one."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any


def finite_or_null(value: Any) -> Any:
    """``value`` with every NaN or infinite float (at any depth) replaced by None: a figure
    without a value (e.g. the ROC AUC of a split holding one class) as JSON's ``null``, which
    strict readers take (``NaN`` is not JSON)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite_or_null(item) for item in value]
    return value


PRIVATE_FOLDER_MODE = 0o700
PRIVATE_FILE_MODE = 0o600
"""Modes of the platform's data (accounts, human EEG, models): its owner's only."""


def private_folder(path: str | Path) -> Path:
    """``path`` as a folder only its owner may enter (created, with its missing parents, or
    its mode set to 700 if it exists)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True, mode=PRIVATE_FOLDER_MODE)
    if path.stat().st_mode & 0o777 != PRIVATE_FOLDER_MODE:
        path.chmod(PRIVATE_FOLDER_MODE)
    return path


def _umask() -> int:
    """The process's umask, read without changing it (Linux: /proc; else the usual 022)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    return 0o022


def write_bytes_atomic(path: str | Path, data: bytes, *, mode: int | None = None) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and rename it.

    The file gets the mode a plain ``open(path, "w")`` would give (0666 less the umask), not
    the temporary file's 0600, so results in a shared folder are readable as the CSVs and
    plots beside them are; ``mode`` sets another (0600 for a secret).
    """
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask() if mode is None else mode)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def write_private_text(path: str | Path, text: str) -> Path:
    """Write a secret to ``path`` atomically, readable by this user alone (mode 0600)."""
    return write_bytes_atomic(path, text.encode(), mode=0o600)


def write_json_atomic(path: str | Path, payload: Any, *, indent: int | None = 2) -> Path:
    """Write ``payload`` as JSON (strict: NaN and infinities are refused) atomically."""
    text = json.dumps(payload, indent=indent, allow_nan=False)
    return write_bytes_atomic(path, (text + "\n").encode())


def write_results_json(path: str | Path, payload: Any, *, indent: int | None = 2) -> Path:
    """Write result figures as strict JSON that other tools read, atomically: a figure
    without a value (NaN, infinite) as ``null`` (Python's ``json`` would write ``NaN``, which
    strict parsers, ``jq`` and browsers refuse, and the whole file with it)."""
    return write_json_atomic(path, finite_or_null(payload), indent=indent)
