"""``bgrl bench loop``'s paced session watched on the subject's real display page: the api
(started by the bench, signed in through its login route) serves the page to Debian's
headless Chromium, the page reports each frame it showed, and the timeline gets the
action -> frame shown figure; without a browser that figure is absent and the reason is
given, and the rest of the timeline is measured the same."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import select

from benchmarks import bench_loop
from services.core.db.live import LiveFrameShown
from services.core.db.models import LabSession
from tests.loop.conftest import TOKEN, LoopPlatform
from tests.loop.test_chain import calibrate

pytestmark = pytest.mark.slow

ACTIONS = 12
"""Enough for frames, decisions and labels on every path; each action is PERIOD_S of real
time plus a learner update, so more only make the test slower."""
PERIOD_S = 0.5


@pytest.fixture(scope="module")
def classifier_id(loop: LoopPlatform) -> int:
    return calibrate(loop)


@pytest.fixture
def services(loop: LoopPlatform) -> Iterator[bench_loop.BenchServices]:
    """The loop's services as the bench holds them; the api it starts is stopped after."""
    urls = {name: loop.url(name) for name in ("sim", "eeg", "learner")}
    started = bench_loop.BenchServices(loop.data_dir, TOKEN, urls, [])
    try:
        yield started
    finally:
        for child in started.children:
            child.terminate()
        for child in started.children:
            child.wait_or_kill(time.monotonic() + 10)


def _paced(loop: LoopPlatform, classifier_id: int, services: bench_loop.BenchServices) -> dict:
    with loop.runtime.sessions() as db:
        subject_id = db.scalar(select(LabSession.subject_id).limit(1))
    assert subject_id is not None
    return bench_loop.paced_session(
        loop.runtime,
        subject_id,
        classifier_id,
        quality=1.0,
        actions=ACTIONS,
        period_s=PERIOD_S,
        services=services,
    )


def test_the_display_page_reports_the_frames_of_the_paced_session(
    loop: LoopPlatform, classifier_id: int, services: bench_loop.BenchServices
) -> None:
    reason = bench_loop.display_unavailable()
    if reason is not None:
        pytest.skip(reason)
    paced = _paced(loop, classifier_id, services)
    assert paced["actions"] == ACTIONS
    display = paced["display"]
    assert "reason" not in display and "error" not in display, display
    assert display["console_errors"] == []
    shown = paced["latency_ms"]["marker_to_frame_shown"]
    assert 0 < shown["n"] == display["frames_reported"] <= ACTIONS
    assert shown["p50_ms"] > 0  # a frame is shown after its action was executed
    with loop.runtime.sessions() as db:
        steps = db.scalars(select(LiveFrameShown.step)).all()
    assert len(steps) == len(set(steps)) and set(steps) <= set(range(ACTIONS))
    assert [s for s in services.children if s.name == "api"], "the bench started the api"
    assert paced["latency_ms"]["epoch_end_to_next_action"]["n"] > 0


def test_without_chromium_the_figure_is_absent_with_the_reason(
    loop: LoopPlatform,
    classifier_id: int,
    services: bench_loop.BenchServices,
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
) -> None:
    monkeypatch.setattr(bench_loop, "CHROMIUM", tmp_path / "no-chromium")
    paced = _paced(loop, classifier_id, services)
    assert paced["actions"] == ACTIONS
    assert str(tmp_path / "no-chromium") in paced["display"]["reason"]
    assert "marker_to_frame_shown" not in paced["latency_ms"]
    assert paced["latency_ms"]["epoch_end_to_next_action"]["n"] > 0  # the rest still runs
    assert services.children == []  # no api started for a display that cannot open
