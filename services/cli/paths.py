"""Output paths of the commands, checked before any work: a one-line error, no traceback."""

from __future__ import annotations

import os
from pathlib import Path

import typer


def refuse_file(path: Path, option: str = "--out") -> None:
    """``BadParameter`` naming ``option`` if the output folder ``path`` is a file (for
    commands that create the folder only once their input has been read)."""
    if path.exists() and not path.is_dir():
        raise typer.BadParameter(f"{path} is a file, not a folder", param_hint=option)


def output_folder(path: Path, option: str = "--out") -> Path:
    """Create the folder ``path`` (and its parents) if needed; ``BadParameter`` naming
    ``option`` if it is a file, lies below one, or cannot be created or written."""
    refuse_file(path, option)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise typer.BadParameter(
            f"cannot create the folder {path}: {reason}", param_hint=option
        ) from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise typer.BadParameter(f"the folder {path} is not writable", param_hint=option)
    return path


def output_file(path: Path, option: str = "--out", suffixes: tuple[str, ...] = ()) -> Path:
    """Check that ``path`` can be written as a file (with one of ``suffixes`` if given) and
    create its folder; ``BadParameter`` naming ``option`` otherwise."""
    if path.is_dir():
        raise typer.BadParameter(f"{path} is a folder, not a file", param_hint=option)
    if suffixes and path.suffix.lower() not in suffixes:
        expected = " or ".join(suffixes)
        raise typer.BadParameter(
            f"{path.name}: the file name must end in {expected}", param_hint=option
        )
    output_folder(path.parent, option)
    return path
