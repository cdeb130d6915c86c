"""The free-space reserve of the data disk: uploads and new jobs stop before the disk fills.

A lab PC runs the platform for weeks; a full disk would corrupt nothing (every file is
written to a temporary name and renamed), but it would fail running jobs' checkpoints and
the database's own writes. So every request that brings new data in (a recording upload, a
new job, a retry) first asks :func:`require_free_space`; below ``BGRL_MIN_FREE_MB`` it is
refused with HTTP 507 and a message naming the folder, the free space and the setting,
before anything is written. A write that still finds the disk full (:func:`is_disk_full`)
is removed and reported the same way.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

from services.core.errors import InsufficientStorageError

MB = 1024 * 1024
MIN_FREE_SETTING = "BGRL_MIN_FREE_MB"
"""Environment variable of the reserve (platform-wide, in every service's settings)."""


def free_bytes(folder: Path) -> int:
    """Bytes free for this user on the disk holding ``folder`` (or its nearest parent that
    exists: a folder not yet created lands on its parent's disk)."""
    path = Path(folder).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def require_free_space(
    *folders: Path, min_free_mb: int, refusing: str, incoming_bytes: int = 0
) -> None:
    """Raise :class:`InsufficientStorageError` (507) unless each folder's disk keeps
    ``min_free_mb`` free after ``incoming_bytes`` more are written there.

    ``refusing`` names what is refused in the message (e.g. ``"the upload"``); a reserve of
    0 turns the check off.
    """
    if min_free_mb <= 0:
        return
    for folder in folders:
        free = free_bytes(folder)
        if free - incoming_bytes < min_free_mb * MB:
            needs = f" and {incoming_bytes / MB:.1f} MB are coming" if incoming_bytes else ""
            raise InsufficientStorageError(
                f"{refusing} is refused: the disk holding {folder} has {free / MB:.0f} MB "
                f"free{needs}, and {MIN_FREE_SETTING} keeps {min_free_mb} MB free; free "
                "some space (or lower the setting) and try again"
            )


def is_disk_full(exc: BaseException) -> bool:
    """True when ``exc`` is the OS saying the disk (or the user's quota) is full."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)
