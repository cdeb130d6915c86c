"""Strict JSON for the benchmarks' result files: what other tools read.

Python's ``json`` writes ``NaN`` and ``Infinity`` by default, which are not JSON (strict
parsers, ``jq``, browsers refuse the whole file). A figure that has no value (e.g. the ROC
AUC of a test split holding one class) is written as ``null`` instead.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from services.core.files import finite_or_null, write_json_atomic


def write_json(path: str | Path, payload: Any, *, indent: int | None = 2) -> Path:
    """Write ``payload`` as strict JSON (non-finite numbers as null), atomically."""
    return write_json_atomic(path, finite_or_null(payload), indent=indent)
