"""Action markers reach an LSL inlet over loopback, with the action's own timestamp."""

from __future__ import annotations

import itertools
import json
import statistics
import threading
import time
import uuid
import warnings
from collections.abc import Iterator

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.core.markers import MARKER_STREAM_NAME, MARKER_STREAM_TYPE, ActionMarker
from services.sim.app import create_app
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient

pytestmark = pytest.mark.lsl


@pytest.fixture(scope="module")
def lsl():
    """The mne_lsl.lsl module, or a skip naming why liblsl cannot run here."""
    try:
        from mne_lsl import lsl as lsl_module

        lsl_module.local_clock()
        probe = lsl_module.StreamInfo("bgrl-probe", "Markers", 1, 0.0, "string", "bgrl-probe")
        lsl_module.StreamOutlet(probe)
    except Exception as exc:  # liblsl missing or unable to open sockets
        pytest.skip(f"liblsl cannot run here: {type(exc).__name__}: {exc}")
    return lsl_module


@pytest.fixture
def source_id() -> str:
    return f"bgrl-sim-test-{uuid.uuid4().hex}"


@pytest.fixture
def service(lsl, source_id: str) -> Iterator[tuple[TestClient, object]]:
    """A sim service publishing markers under a unique source_id, and an open inlet on it."""
    settings = SimSettings(lsl_markers=True, marker_source_id=source_id)
    with TestClient(create_app(settings)) as client:
        infos = lsl.resolve_streams(timeout=10.0, source_id=source_id, minimum=1)
        assert len(infos) == 1, "the sim's marker stream was not found on loopback"
        info = infos[0]
        assert (info.name, info.stype, info.n_channels) == (MARKER_STREAM_NAME, "Markers", 1)
        assert info.stype == MARKER_STREAM_TYPE
        inlet = lsl.StreamInlet(info)
        inlet.open_stream(timeout=10.0)
        try:
            yield client, inlet
        finally:
            inlet.close_stream()


def pull_markers(inlet, n: int) -> list[tuple[ActionMarker, float]]:
    received = []
    for _ in range(n):
        sample, timestamp = inlet.pull_sample(timeout=10.0)
        assert timestamp is not None, f"only {len(received)} of {n} markers arrived"
        received.append((ActionMarker.from_lsl(sample[0]), timestamp))
    return received


def test_step_markers_arrive_with_the_action_timestamp(service) -> None:
    client, inlet = service
    health = client.get("/health").json()
    assert health["lsl_markers"] is True and health["marker_stream"] == MARKER_STREAM_NAME
    sid = client.post("/sessions", json={"seed": 0}).json()["id"]
    sent = [
        client.post(f"/sessions/{sid}/step", json={"action": action}).json()["marker"]
        for action in (0, 1, 2)
    ]
    received = pull_markers(inlet, 3)
    for expected, (marker, timestamp) in zip(sent, received, strict=True):
        assert marker == ActionMarker.model_validate(expected)
        assert timestamp == pytest.approx(marker.timestamp, abs=1e-6)
    assert [m.step for m, _ in received] == [0, 1, 2]
    assert all(m.correct is not None for m, _ in received)


def test_paced_mode_markers_are_evenly_spaced(service) -> None:
    client, inlet = service
    sid = client.post("/sessions", json={"seed": 1}).json()["id"]
    period = 0.1
    body = {"policy": "random", "period_s": period, "max_actions": 8, "auto_reset": True}
    assert client.post(f"/sessions/{sid}/paced", json=body).status_code == 201
    received = pull_markers(inlet, 8)
    stamps = [timestamp for _, timestamp in received]
    intervals = [b - a for a, b in itertools.pairwise(stamps)]
    # A reset tick (after a collision) takes one period without an action; a late tick
    # shortens the next interval (the schedule does not drift).
    assert all(0.0 < i < period * 2.5 + 0.1 for i in intervals), intervals
    assert statistics.median(intervals) == pytest.approx(period, abs=0.03)
    assert {m.session_id for m, _ in received} == {sid}


def _without_local_time(line: str) -> dict:
    """A ``bgrl sim markers`` line as a marker: the CLI adds the receiver's ``local_time``."""
    entry = json.loads(line)
    assert isinstance(entry.pop("local_time"), float)
    return entry


def test_cli_prints_markers(service, source_id: str) -> None:
    client, _ = service
    sid = client.post("/sessions", json={"seed": 0}).json()["id"]
    args = ["sim", "markers", "--count", "2", "--timeout", "10", "--source-id", source_id]
    result: dict[str, object] = {}
    listener = threading.Thread(target=lambda: result.update(run=CliRunner().invoke(app, args)))
    listener.start()
    deadline = time.monotonic() + 15.0
    while listener.is_alive() and time.monotonic() < deadline:  # until the CLI's inlet is up
        client.post(f"/sessions/{sid}/step", json={"action": 1})
        time.sleep(0.2)
    listener.join(timeout=5.0)
    run = result["run"]
    assert run.exit_code == 0, run.output
    lines = [line for line in run.stdout.splitlines() if line.startswith("{")]
    markers = [ActionMarker.model_validate(_without_local_time(line)) for line in lines]
    assert len(markers) == 2 and {m.session_id for m in markers} == {sid}
