"""The systemd units shipped for a lab PC (deploy/systemd) pass ``systemd-analyze verify``
and keep the settings docs/deploy.md relies on."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

UNITS = Path(__file__).resolve().parents[1] / "deploy" / "systemd"
INSTALLED_BGRL = "/opt/bgrl/venv/bin/bgrl"
"""Where the units expect the platform (docs/deploy.md installs it there)."""


def _settings(unit: str) -> dict[str, list[str]]:
    """Every ``key=value`` of a unit file (keys may repeat)."""
    values: dict[str, list[str]] = {}
    for line in (UNITS / unit).read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", ";", "[")):
            key, _, value = line.partition("=")
            values.setdefault(key.strip(), []).append(value.strip())
    return values


def test_the_service_restarts_on_failure_as_its_own_user_and_leaves_no_orphans() -> None:
    service = _settings("bgrl.service")
    assert service["Restart"] == ["on-failure"]
    assert service["KillMode"][0] in ("mixed", "control-group")
    assert service["User"] == ["bgrl"]
    assert service["EnvironmentFile"] == ["/etc/bgrl/bgrl.env"]
    assert service["ExecStart"] == [f"{INSTALLED_BGRL} up"]
    assert service["StateDirectoryMode"] == ["0700"]
    assert service["UMask"] == ["0077"]
    timeout_s = int(service["TimeoutStopSec"][0])
    assert timeout_s > 10  # bgrl up stops everything within 10 s before systemd kills
    backup = _settings("bgrl-backup.service")
    assert backup["User"] == ["bgrl"] and backup["UMask"] == ["0077"]
    assert f"{INSTALLED_BGRL} backup" in backup["ExecStart"][0]


def test_units_pass_systemd_analyze_verify(tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed (Debian: apt-get install systemd)")
    bgrl = Path(sys.executable).with_name("bgrl")
    if not bgrl.is_file():
        pytest.skip(f"no bgrl command beside {sys.executable} to stand in for {INSTALLED_BGRL}")
    names = sorted(p.name for p in UNITS.iterdir() if p.suffix in (".service", ".timer"))
    assert names == ["bgrl-backup.service", "bgrl-backup.timer", "bgrl.service"]
    for name in names:  # verify checks that ExecStart's program exists: use this one
        text = (UNITS / name).read_text().replace(INSTALLED_BGRL, str(bgrl))
        (tmp_path / name).write_text(text)
    result = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", *names],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=False,
        timeout=120,
    )
    # a key systemd cannot parse is only a warning (exit 0): no output at all is the bar
    assert (result.returncode, result.stdout + result.stderr) == (0, "")
