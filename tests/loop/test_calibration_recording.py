"""A calibration session streams through the EEG service's live recording: the stream and
its markers are written to disk as they arrive, survive a crash of the EEG service, and are
stored at the end (BDF + sha256, a recording row) before the eeg_calibration job."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import pytest

from services.core.db.live import LiveRun
from services.core.db.models import Job, Recording
from services.eeg.recordings.io import read_recording
from services.worker.live_session import live_session
from services.worker.runtime import run_job
from tests.loop.conftest import TOKEN, LoopPlatform
from tests.loop.test_chain import wait_for

pytestmark = pytest.mark.slow


def _folder(loop: LoopPlatform, run_id: int) -> Path:
    return loop.data_dir / "eeg" / "live_recordings" / f"live-run-{run_id}-calibration"


def _markers_on_disk(folder: Path) -> int:
    try:
        return (folder / "index.jsonl").read_bytes().count(b'"kind": "marker"')
    except FileNotFoundError:
        return 0


def _start(loop: LoopPlatform, n_actions: int) -> tuple[int, str, threading.Thread, list[str]]:
    session_id = loop.lab_session("calibration", subject_code="S-REC")
    options = {"accelerated": True, "n_actions": n_actions, "virtual_quality": 0.9, "seed": 4}
    run_id, job_id = loop.live_job(session_id, options)
    outcome: list[str] = []
    worker = threading.Thread(
        target=lambda: outcome.append(run_job(loop.runtime, job_id, live_session))
    )
    worker.start()
    return run_id, job_id, worker, outcome


def _stored(loop: LoopPlatform, run_id: int) -> tuple[LiveRun, Recording, dict]:
    with loop.runtime.sessions() as db:
        run = db.get(LiveRun, run_id)
        assert run is not None and run.status == "completed", run and run.error
        recording = db.get(Recording, run.recording_id)
        assert recording is not None
        follow_up = db.get(Job, run.follow_up_job_id)
        assert follow_up is not None and follow_up.kind == "eeg_calibration"
        assert follow_up.config["recording_id"] == recording.id
        db.expunge_all()
    eeg = httpx.get(
        f"{loop.url('eeg')}/recordings/{recording.sha256}",
        headers={"X-Service-Token": TOKEN},
        timeout=10,
    )
    assert eeg.status_code == 200, eeg.text
    return run, recording, eeg.json()


def test_calibration_is_the_eeg_services_live_recording_written_as_it_runs(
    loop: LoopPlatform,
) -> None:
    n_actions = 120
    run_id, _, worker, outcome = _start(loop, n_actions)
    folder = _folder(loop, run_id)
    counts_on_disk = set()
    while worker.is_alive():  # the index grows block by block while the session runs
        counts_on_disk.add(_markers_on_disk(folder))
        time.sleep(0.01)
    worker.join()
    assert outcome == ["succeeded"]
    assert any(0 < n < n_actions for n in counts_on_disk), sorted(counts_on_disk)
    run, recording, stored = _stored(loop, run_id)
    assert run.result is not None and run.result["recording_sha256"] == recording.sha256
    assert stored["n_actions"] == n_actions and stored["synthetic"] and recording.synthetic
    assert run.result["errors"] == stored["n_errors"]
    assert not folder.exists()  # finalised: the folder became the stored BDF
    raw = read_recording(loop.runtime.store.path(_relpath(loop, recording)))
    assert raw.info["sfreq"] == stored["sfreq"] == recording.sfreq


def _relpath(loop: LoopPlatform, recording: Recording) -> str:
    from services.core.db.models import Artifact

    with loop.runtime.sessions() as db:
        artifact = db.get(Artifact, recording.artifact_id)
        assert artifact is not None and artifact.sha256 == recording.sha256
        return artifact.relpath


def test_a_calibration_survives_an_eeg_service_crash(loop: LoopPlatform) -> None:
    """The recording folder keeps every flushed block; the restarted EEG service continues
    it and the session stores one recording (at most the markers of the unflushed block
    and the one in flight are lost)."""
    n_actions = 80
    run_id, _, worker, outcome = _start(loop, n_actions)
    folder = _folder(loop, run_id)
    wait_for(lambda: _markers_on_disk(folder) >= 20 or bool(outcome))
    assert not outcome, "the session ended before the EEG service could be killed"
    loop.kill("eeg")
    loop.start("eeg")
    worker.join(timeout=600)
    assert outcome == ["succeeded"]
    run, _, stored = _stored(loop, run_id)
    assert run.result is not None and run.result["actions"] == n_actions
    assert n_actions - 3 <= stored["n_actions"] <= n_actions
    assert any("gap" in note for note in stored["notes"])


def test_a_headset_calibration_over_lsl_is_recorded_by_the_eeg_service(
    loop: LoopPlatform,
) -> None:
    """``eeg_source: lsl``: the EEG service connects the stream without a classifier,
    records it with the sim's markers in real time, and the session stores it."""
    from services.eeg.live import lsl
    from services.eeg.virtual.subject import simulate_recording

    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    raw = simulate_recording([True, False] * 14, quality=1.0, seed=5, sfreq=512.0)
    name = f"bgrl-headset-{time.monotonic_ns()}"
    player = lsl.replay(raw, name=name, chunk_size=16)
    try:
        session_id = loop.lab_session("calibration", subject_code="S-LSL")
        n_actions = 8
        options = {"eeg_source": "lsl", "stream_name": name, "n_actions": n_actions,
                   "period_s": 0.5, "seed": 2}  # fmt: skip
        run_id, job_id = loop.live_job(session_id, options)
        assert run_job(loop.runtime, job_id, live_session) == "succeeded"
    finally:
        player.stop()
    run, recording, stored = _stored(loop, run_id)
    assert stored["n_actions"] == n_actions and stored["sfreq"] == 512.0
    assert run.result is not None and run.result["recorded_markers"] == n_actions
    assert recording.sfreq == 512.0 and stored["duration_s"] >= n_actions * 0.5
