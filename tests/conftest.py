"""Test-wide setup: LSL stays on loopback, services write below a temporary folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import services.core

LSL_LOOPBACK_CFG = Path(services.core.__file__).with_name("lsl_loopback.cfg")
os.environ.setdefault("LSLAPICFG", str(LSL_LOOPBACK_CFG))
os.environ.setdefault("MPLBACKEND", "Agg")
# The free-space reserve (1024 MB by default) would refuse uploads and jobs on a CI machine
# with a nearly full disk; the reserve's own tests set it explicitly.
os.environ.setdefault("BGRL_MIN_FREE_MB", "1")


@pytest.fixture(autouse=True)
def _isolated_data_dir(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch):
    """Every test writes service data (caches, uploads, models) below its own temp folder."""
    monkeypatch.setenv("BGRL_DATA_DIR", str(tmp_path_factory.mktemp("data")))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under pytest-xdist (``make test`` runs two test processes, ``--dist loadgroup``) a
    module's tests run in one process, so its module-scoped platform starts once; the
    network-namespace deployments all run in one process, one after another (each builds
    namespaces, a subnet and compose hosts that two processes at once would fight over)."""
    for item in items:
        netns = item.get_closest_marker("netns") is not None
        group = "netns" if netns else item.nodeid.split("::", 1)[0]
        item.add_marker(pytest.mark.xdist_group(group))
