"""Test-wide setup: LSL stays on loopback, services write below a temporary folder."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """Under pytest-xdist (``make test`` runs two test processes) a module's tests run in one
    process, in order, so its module-scoped platform starts once; the network-namespace
    deployments (tests/deploy) all run in one process, one after another: each builds
    namespaces and a whole compose platform, two of which at once would starve the rest."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "tests/deploy" if module.startswith("tests/deploy/") else module

    return ModuleScheduling(config, log)
