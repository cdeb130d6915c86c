"""Fixtures of the learner service tests: an app on a temporary data folder."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.core.platform import PlatformSettings
from services.learner.service.app import create_app
from services.learner.service.settings import LearnerSettings


@pytest.fixture
def make_client(tmp_path: Path) -> Callable[..., Iterator[TestClient]]:
    """``with make_client(data_dir=..., **settings) as client`` starts a fresh app instance."""

    @contextmanager
    def factory(data_dir: Path = tmp_path, **overrides: object) -> Iterator[TestClient]:
        settings = LearnerSettings(data_dir=data_dir, **overrides)
        platform = PlatformSettings(data_dir=data_dir)
        with TestClient(create_app(settings, platform)) as client:
            yield client

    return factory


@pytest.fixture
def client(make_client) -> Iterator[TestClient]:
    """A learner service on the test's data folder."""
    with make_client() as c:
        yield c
