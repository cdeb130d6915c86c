"""The data disk's free-space reserve: the check, and artifact writes refused with 507.

The reserve (``BGRL_MIN_FREE_MB``) is set above the disk's free space instead of filling
the disk; a real ENOSPC is met on a 2 MB tmpfs in a private mount namespace (``unshare``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from services.core.artifacts import ArtifactStore, DiskReserve
from services.core.disk import MB, free_bytes, require_free_space
from services.core.errors import InsufficientStorageError

REPO = Path(__file__).resolve().parents[2]
ABOVE_FREE_MB = 10**9
"""A reserve larger than any disk here: every check refuses."""


def _files_below(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def test_the_check_names_the_folder_the_free_space_and_the_setting(tmp_path: Path) -> None:
    require_free_space(tmp_path, min_free_mb=1, refusing="the upload")
    require_free_space(tmp_path, min_free_mb=0, refusing="the upload")  # 0: off
    with pytest.raises(InsufficientStorageError) as refused:
        require_free_space(tmp_path / "not" / "yet", min_free_mb=ABOVE_FREE_MB, refusing="x")
    assert refused.value.status_code == 507
    message = str(refused.value)
    assert str(tmp_path / "not" / "yet") in message and "BGRL_MIN_FREE_MB" in message
    free_mb = free_bytes(tmp_path) // MB
    with pytest.raises(InsufficientStorageError, match="are coming"):  # the announced size
        require_free_space(
            tmp_path, min_free_mb=1, refusing="the upload", incoming_bytes=(free_mb + 1) * MB
        )


def test_a_stream_into_the_reserve_is_refused_and_removed(tmp_path: Path) -> None:
    store = ArtifactStore(tmp_path / "store")
    with pytest.raises(InsufficientStorageError):
        store.put_stream(
            [b"x" * 10], kind="recording", name="a.bdf", reserve=DiskReserve(ABOVE_FREE_MB)
        )
    assert _files_below(store.root) == []
    announced = DiskReserve.for_upload(1, str(free_bytes(tmp_path)))
    with pytest.raises(InsufficientStorageError, match="are coming"):
        store.put_stream([b"x"], kind="recording", name="a.bdf", reserve=announced)
    assert _files_below(store.root) == []
    kept = store.put_stream([b"x" * 10], kind="recording", name="a.bdf", reserve=DiskReserve(1))
    assert _files_below(store.root) == [store.path(kept.relpath)]


ENOSPC_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from services.core.artifacts import ArtifactStore
    from services.core.errors import InsufficientStorageError

    store = ArtifactStore(Path(sys.argv[1]))
    try:
        store.put_stream((b"x" * 65536 for _ in range(64)), kind="recording", name="big.bdf")
    except InsufficientStorageError as exc:
        left = [str(p) for p in store.root.rglob("*") if p.is_file()]
        print(exc.status_code, left, str(exc))
    """
)


def test_a_disk_that_fills_during_the_write_is_a_507_and_leaves_no_part(tmp_path: Path) -> None:
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        pytest.skip("needs unshare and mount (util-linux) for a private 2 MB tmpfs")
    mount_point = tmp_path / "small"
    mount_point.mkdir()
    script = tmp_path / "fill.py"
    script.write_text(ENOSPC_SCRIPT)
    probe = subprocess.run(
        ["unshare", "-rm", "mount", "-t", "tmpfs", "-o", "size=2m", "none", str(mount_point)],
        capture_output=True,
        check=False,
    )
    if probe.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs in a user namespace here: {probe.stderr.decode()}")
    result = subprocess.run(
        [
            "unshare",
            "-rm",
            "sh",
            "-c",
            f'mount -t tmpfs -o size=2m none "$1" && exec "{sys.executable}" "$2" "$1"',
            "sh",
            str(mount_point),
            str(script),
        ],
        capture_output=True,
        text=True,
        check=False,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("507 [] "), result.stdout  # 4 MB into 2 MB: nothing kept
    assert "is full: nothing was stored" in result.stdout
