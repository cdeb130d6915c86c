"""The soak benchmark's short version: ``bgrl up`` under load while random processes are
SIGKILLed loses no job, no upload and no live session and leaves no orphan (``bgrl bench
soak`` runs it for longer)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from benchmarks.bench_soak import run_soak

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux")


@pytest.mark.slow
def test_a_short_soak_loses_no_job_and_leaves_no_orphan(tmp_path: Path) -> None:
    report = run_soak(
        tmp_path, minutes=0.5, kill_every_s=8, job_every_s=10, upload_every_s=10,
        live_every_s=30, live_actions=30, job_steps=256, drain_s=400, seed=1,
    )  # fmt: skip
    jobs = report["jobs"]
    assert jobs["by_kind"]["guided_ppo"]["submitted"] >= 1
    assert jobs["by_kind"]["live_session"]["submitted"] >= 1
    assert jobs["lost"] == 0, report
    assert jobs["succeeded"] + jobs["failed_with_reason"] == jobs["submitted"]
    uploads = report["uploads"]
    assert uploads["submitted"] >= 1
    assert uploads["lost"] == 0, report
    assert uploads["stored"] >= 1
    assert (
        uploads["stored"] + uploads["refused_with_reason"] + uploads["unanswered"]
        == (uploads["submitted"])
    )
    live = report["live_sessions"]
    assert live["started"] >= 1
    assert live["lost"] == 0, report
    assert live["ended_with_data"] + live["ended_with_reason"] == live["started"]
    assert report["orphans"] == 0
    kills = sum(report["kills"].values())
    assert kills >= 2
    # every killed process bgrl up started came back (a Celery or uvicorn child that was
    # killed is replaced by its parent, which bgrl up does not count)
    assert sum(report["restarts"].values()) >= report["kills_of_supervised"]
    assert report["reads"]["count"] > 0 and report["reads"]["p99_ms"] is not None
    assert (tmp_path / "soak_rss.png").stat().st_size > 0
    assert report["rss_mib"]["api"]["processes"] >= 1
