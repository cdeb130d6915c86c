"""Log files in BGRL_LOG_DIR: one per service, rotated by size, safe for several processes."""

from __future__ import annotations

import logging
import os
import re
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

from services.core.logging import configure_log_file
from services.core.settings import BaseServiceSettings

REPO = Path(__file__).resolve().parents[2]
LINES_PER_PROCESS = 3000
PAD = "x" * 200

WRITER = textwrap.dedent(
    f"""
    import logging, sys, time
    from pathlib import Path
    from services.core.logging import configure_log_file, configure_logging
    from services.core.settings import BaseServiceSettings

    configure_logging("INFO")
    settings = BaseServiceSettings(log_dir=sys.argv[1], log_max_mb=1, log_backups=1)
    configure_log_file(settings, "api")
    configure_log_file(settings, "api")  # twice: still one handler, each line once
    log = logging.getLogger("writer")
    folder = Path(sys.argv[1])
    (folder / f"ready-{{sys.argv[2]}}").touch()
    while not (folder / "go").exists():  # both write at once
        time.sleep(0.01)
    for i in range({LINES_PER_PROCESS}):
        log.info("writer=%s line=%d {PAD}", sys.argv[2], i)
        if i % 50 == 0:
            time.sleep(0.002)  # let the other writer's lines in between
    """
)


def test_two_processes_share_a_rotated_file_and_lose_no_line(tmp_path: Path) -> None:
    """Two writers of 0.8 MB each through 1 MB files keeping one backup: every line is kept
    once. (Python's own RotatingFileHandler loses about two thirds of them here: a process
    rotates away, then deletes, the file the other still writes to.)"""
    folder = tmp_path / "logs"
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    writers = [
        subprocess.Popen(
            [sys.executable, str(script), str(folder), name],
            env=env,
            stderr=subprocess.DEVNULL,
        )
        for name in ("a", "b")
    ]
    while not all((folder / f"ready-{name}").exists() for name in ("a", "b")):
        assert all(w.poll() is None for w in writers), "a writer died before writing"
        time.sleep(0.05)
    (folder / "go").touch()
    assert [w.wait(timeout=300) for w in writers] == [0, 0]

    files = sorted(p for p in folder.iterdir() if re.fullmatch(r"api\.log(\.\d+)?", p.name))
    assert len(files) == 2, files  # 1.6 MB written at 1 MB a file: rotated once
    seen: dict[str, list[int]] = {"a": [], "b": []}
    for path in files:
        assert path.stat().st_size <= 1024 * 1024 + 1000, path
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        for line in path.read_text().splitlines():
            found = re.search(r"writer=(\w) line=(\d+) x+$", line)
            assert found, line
            seen[found[1]].append(int(found[2]))
    assert {name: sorted(lines) for name, lines in seen.items()} == {
        name: list(range(LINES_PER_PROCESS)) for name in ("a", "b")
    }
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700


def test_no_log_folder_means_stderr_only(tmp_path: Path) -> None:
    handlers = list(logging.getLogger().handlers)
    assert configure_log_file(BaseServiceSettings(log_dir=None), "api") is None
    assert logging.getLogger().handlers == handlers
