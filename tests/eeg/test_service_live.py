"""The EEG service's live side without LSL hardware: websocket close codes, replacement of
the ingest connection, bad numbers, microvolt epochs, the marker thread (malformed markers
and failures) and what GET /live reports."""

from __future__ import annotations

import json
import time
from typing import ClassVar

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from services.core.markers import ActionMarker
from services.eeg.live import lsl
from services.eeg.live.ingest import LiveIngest
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from tests.eeg.test_virtual_source import save_untrained_classifier

SFREQ = 512.0
EEG = ["FCz", "Cz", "Pz"]
STREAM = [*EEG, STIM_CHANNEL]
CLASSIFIER = "plumbing"
MARKER = {"session_id": "s", "step": 0, "episode": 0, "action": 0, "timestamp": 0.0}


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, epoch_wait_s=0.5)
    with TestClient(create_app(settings)) as c:
        save_untrained_classifier(c, EEG, CLASSIFIER, SFREQ)
        yield c


def _disconnect_code(ws) -> tuple[int, str]:
    with pytest.raises(WebSocketDisconnect) as info:
        ws.receive_json()
    return info.value.code, info.value.reason


def _noise(seconds: float, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(0.0, 20e-6, size=(int(seconds * SFREQ), len(STREAM)))
    x[:, -1] = 0.0
    return x


# ------------------------------------------------------------------ numbers and units
@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('{"epoch": [[0]], "ch_names": ["FCz"], "sfreq": NaN}', "sfreq"),
        ('{"epoch": [[0]], "ch_names": ["FCz"], "sfreq": Infinity}', "sfreq"),
        ('{"epoch": [[0]], "ch_names": ["FCz"], "sfreq": 1e400}', "sfreq"),
        ('{"epoch": [[0]], "ch_names": ["FCz"], "sfreq": 128, "volts": true}', "volts"),
    ],
)
def test_classify_refuses_non_finite_rates_naming_the_field(client, text, field):
    response = client.post(
        f"/classifiers/{CLASSIFIER}/classify",
        content=text,
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 422
    assert response.json()["detail"][0]["field"] == field


def test_classify_refuses_microvolts_and_nan_epochs(client):
    url = f"/classifiers/{CLASSIFIER}/classify"
    volts = np.random.default_rng(0).normal(0.0, 5e-6, size=(3, 103))
    body = {"epoch": volts.tolist(), "ch_names": EEG, "sfreq": 128.0}
    ok = client.post(url, json=body)
    assert ok.status_code == 200 and ok.json()["status"] == "ok"
    micro = client.post(url, json={**body, "epoch": (volts * 1e6).tolist()})
    assert micro.status_code == 422
    peak = float(np.max(np.abs(volts * 1e6)))
    assert micro.json() == {
        "detail": f"epoch amplitudes reach {peak:.3g}, which looks like microvolts; send "
        "volts (|x| <= 0.01)",
        "field": "epoch",
    }
    nan = volts.tolist()
    nan[1][5] = float("nan")
    response = client.post(
        url,
        content=json.dumps({**body, "epoch": nan}),  # json.dumps writes NaN
        headers={"content-type": "application/json"},
    )
    assert response.status_code == 422
    assert response.json() == {"detail": "epoch contains NaN or infinite values", "field": "epoch"}


@pytest.mark.parametrize(
    ("field", "value"),
    [("timestamp", "NaN"), ("timestamp", "Infinity"), ("timestamp", "1e400"), ("step", "1e400")],
)
def test_markers_with_non_finite_numbers_are_a_422_naming_the_field(client, field, value):
    text = json.dumps({**MARKER, field: "@"}).replace('"@"', value)
    response = client.post(
        "/live/markers", content=text, headers={"content-type": "application/json"}
    )
    assert response.status_code == 422, response.text
    assert response.json()["detail"][0]["field"] == field
    typo = client.post("/live/markers", json={**MARKER, "stepp": 1})
    assert typo.status_code == 422 and typo.json()["detail"][0]["field"] == "stepp"


def test_action_marker_refuses_nan_so_it_can_always_be_broadcast():
    with pytest.raises(ValueError, match="timestamp"):
        ActionMarker(**{**MARKER, "timestamp": float("nan")})
    with pytest.raises(ValueError, match=r"timestamp\n  Input should be a finite number"):
        ActionMarker.from_lsl(json.dumps({**MARKER, "timestamp": float("nan")}))


# ------------------------------------------------------------------ websocket close codes
def test_foreign_origin_is_closed_with_4403_before_accept(client):
    for url in ("/live/feedback", f"/live/ingest?classifier_id={CLASSIFIER}"):
        with (
            pytest.raises(WebSocketDisconnect) as info,
            client.websocket_connect(url, headers={"origin": "http://evil.example"}),
        ):
            pass
        assert (info.value.code, info.value.reason) == (4403, "origin not allowed")
    same_host = {"origin": "http://testserver"}
    with client.websocket_connect("/live/feedback", headers=same_host) as ws:
        ws.send_text("ping")  # accepted: client messages are ignored


def test_unknown_classifier_is_accepted_then_closed_with_4404(client):
    with client.websocket_connect("/live/ingest?classifier_id=missing") as ws:
        assert ws.receive_json() == {"ok": False, "error": "no classifier 'missing'"}
        assert _disconnect_code(ws) == (4404, "no classifier 'missing'")


@pytest.mark.parametrize(
    ("first", "reason"),
    [
        ("hello", "the first message is not JSON: 'hello'"),
        ('{"ch_names": ["FCz"]}', "bad header: sfreq: Field required"),
        (
            '{"ch_names": ["FCz", "Cz", "Pz"], "sfreq": NaN}',
            "bad header: sfreq: Input should be a finite number",
        ),
        ('{"ch_names": ["FCz", "Cz"], "sfreq": 512}', "stream lacks channels Pz"),
    ],
)
def test_malformed_first_ingest_message_closes_with_4422(client, first, reason):
    with client.websocket_connect(f"/live/ingest?classifier_id={CLASSIFIER}") as ws:
        ws.send_text(first)
        assert ws.receive_json() == {"ok": False, "error": reason}
        assert _disconnect_code(ws) == (4422, reason)
    assert client.get("/live").json()["connected"] is False


def test_bad_classifier_query_closes_with_4422(client):
    url = "/live/ingest?classifier_id=" + "x" * 65
    with client.websocket_connect(url) as ws:
        message = ws.receive_json()
        assert message["message"] == "classifier_id: String should have at most 64 characters"
        assert _disconnect_code(ws)[0] == 4422


def test_binary_ingest_chunks_equal_json_ones_and_bad_ones_are_refused(client):
    """A binary chunk (float64 first timestamp, float32 samples) is ingested exactly as the
    same float32 samples sent as JSON; a chunk of the wrong size is refused with the reason
    and the connection stays open."""
    import struct

    url = f"/live/ingest?classifier_id={CLASSIFIER}"
    header = {"ch_names": STREAM, "sfreq": SFREQ}
    x = _noise(3.0).astype(np.float32)
    onset = 11.0
    epochs = []
    for binary in (False, True):
        with client.websocket_connect(url) as ws:
            ws.send_json(header)
            assert ws.receive_json() == {"ok": True, "n_samples": 0}
            if binary:
                bad = struct.pack("<d", 10.0) + x[:3].tobytes()[:-4]
                ws.send_bytes(bad)
                answer = ws.receive_json()
                assert answer["ok"] is False and "float32" in answer["error"]
                ws.send_bytes(struct.pack("<d", 10.0) + x.tobytes())
            else:
                ws.send_json({"first_timestamp": 10.0, "samples": x.tolist()})
            assert ws.receive_json() == {"ok": True, "n_samples": len(x)}
            result = client.app.state.service.live.ingest.epoch_for(onset)
            assert result.status == "ok", result.reason
            epochs.append(result.epoch)
    np.testing.assert_array_equal(epochs[0], epochs[1])


def test_second_ingest_websocket_replaces_the_first(client):
    url = f"/live/ingest?classifier_id={CLASSIFIER}"
    header = {"ch_names": STREAM, "sfreq": SFREQ}
    x = _noise(1.0)
    with client.websocket_connect(url) as first:
        first.send_json(header)
        assert first.receive_json() == {"ok": True, "n_samples": 0}
        first.send_json({"first_timestamp": 10.0, "samples": x.tolist()})
        assert first.receive_json() == {"ok": True, "n_samples": 512}
        with client.websocket_connect(url) as second:
            second.send_json(header)
            assert second.receive_json() == {"ok": True, "n_samples": 0}
            reason = "replaced by a new WS /live/ingest"
            assert first.receive_json() == {"ok": False, "error": reason}
            assert _disconnect_code(first) == (4410, reason)
            second.send_json({"first_timestamp": 50.0, "samples": x[:256].tolist()})
            assert second.receive_json() == {"ok": True, "n_samples": 256}
            status = client.get("/live").json()
            assert (status["connected"], status["source"], status["n_samples"]) == (
                True,
                "websocket",
                256,
            )
            client.delete("/live")
            reason = "disconnected by DELETE /live"
            assert second.receive_json() == {"ok": False, "error": reason}
            assert _disconnect_code(second) == (4410, reason)


# ------------------------------------------------------------------ LSL marker thread
class FakeEegSource:
    """Stands in for LslEegIngest: an ingest the test feeds directly."""

    instances: ClassVar[list[FakeEegSource]] = []
    synthetic = False

    def __init__(self, name, *, eeg_ch_names, params, timeout, channel_map=None):
        self.ingest = LiveIngest(STREAM, SFREQ, eeg_ch_names=eeg_ch_names, params=params)
        self.closed = False
        FakeEegSource.instances.append(self)

    @property
    def error(self) -> str | None:
        return None

    def close(self) -> None:
        self.closed = True
        self.ingest.mark_disconnected("LSL inlet closed")


class FakeStreamInlet:
    """Stands in for mne_lsl's StreamInlet: scripted chunks of marker strings."""

    def __init__(self, chunks: list[tuple[list[str], list[float]] | Exception]) -> None:
        self.chunks = chunks
        self.closed = False

    def pull_chunk(self, timeout: float = 0.0):
        if not self.chunks:
            time.sleep(timeout)
            return [], np.empty(0)
        chunk = self.chunks.pop(0)
        if isinstance(chunk, Exception):
            raise chunk
        texts, stamps = chunk
        return [[text] for text in texts], np.asarray(stamps)

    def close_stream(self) -> None:
        self.closed = True


def _connect_with_markers(client, monkeypatch, chunks) -> tuple[FakeEegSource, FakeStreamInlet]:
    stream_inlet = FakeStreamInlet(chunks)
    real = lsl.MarkerInlet

    def marker_inlet(name, *, timeout):
        inlet = real.__new__(real)  # the real pull(), on a scripted inlet
        inlet._inlet = stream_inlet
        return inlet

    FakeEegSource.instances.clear()
    monkeypatch.setattr(lsl, "LslEegIngest", FakeEegSource)
    monkeypatch.setattr(lsl, "MarkerInlet", marker_inlet)
    response = client.post(
        "/live", json={"classifier_id": CLASSIFIER, "stream_name": "eeg", "marker_stream": "m"}
    )
    assert response.status_code == 200, response.text
    assert (response.json()["source"], response.json()["marker_stream"]) == ("lsl", "m")
    return FakeEegSource.instances[-1], stream_inlet


def _wait_for(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_malformed_marker_is_skipped_and_the_rest_of_its_chunk_classified(client, monkeypatch):
    t0 = 100.0
    texts = [
        ActionMarker(**{**MARKER, "step": 1, "timestamp": t0 + 1.5}).to_lsl(),
        '{"session_id": "s", "step": 2, "episode": 0, "action": 0, "timestamp": NaN}',
        ActionMarker(**{**MARKER, "step": 3, "timestamp": t0 + 2.0}).to_lsl(),
    ]
    with client.websocket_connect("/live/feedback") as feedback:
        source, inlet = _connect_with_markers(client, monkeypatch, [])
        source.ingest.push_chunk(_noise(4.0), first_timestamp=t0)
        inlet.chunks.append((texts, [200.0, 200.5, 201.0]))
        first, second = feedback.receive_json(), feedback.receive_json()
    assert [(m["step"], m["status"]) for m in (first, second)] == [(1, "ok"), (3, "ok")]
    status = client.get("/live").json()
    assert status["issues"] == [
        {
            "kind": "bad_marker",
            "start": 200.5,
            "end": 200.5,
            "detail": "invalid action marker: timestamp: Input should be a finite number",
        }
    ]
    assert status["error"] is None
    client.delete("/live")
    assert source.closed and inlet.closed


def test_marker_thread_failure_shows_in_live_status(client, monkeypatch):
    source, inlet = _connect_with_markers(client, monkeypatch, [])
    source.ingest.push_chunk(_noise(0.5), first_timestamp=10.0)
    assert client.get("/live").json()["connected"] is True
    inlet.chunks.append(OSError("marker stream lost"))
    _wait_for(lambda: client.get("/live").json()["error"] is not None)
    status = client.get("/live").json()
    assert status["connected"] is False
    assert status["error"] == "marker stream 'm' failed: OSError: marker stream lost"
    assert inlet.closed
    assert status["issues"][-1]["kind"] == "disconnect"
    client.delete("/live")
    assert source.closed


def test_live_status_lists_the_last_issues_and_counts_the_dropped(client):
    url = f"/live/ingest?classifier_id={CLASSIFIER}"
    with client.websocket_connect(url) as ws:
        ws.send_json({"ch_names": STREAM, "sfreq": SFREQ})
        ws.receive_json()
        x = _noise(0.1)
        t = 0.0
        for _ in range(105):  # 10 samples lost before every chunk: 104 dropped_samples issues
            ws.send_json({"first_timestamp": t, "samples": x.tolist()})
            assert ws.receive_json()["ok"] is True
            t += (len(x) + 10) / SFREQ
        status = client.get("/live").json()
    assert len(status["issues"]) == 100 and status["issues_dropped"] == 4
    assert {issue["kind"] for issue in status["issues"]} == {"dropped_samples"}


# ------------------------------------------------------------------ real LSL (loopback)
@pytest.mark.lsl
def test_live_lsl_source_classifies_markers(client):
    from mne_lsl.lsl import resolve_streams

    from services.eeg.virtual.subject import simulate_recording
    from services.sim.lsl_markers import MarkerPublisher

    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    labels = [True, False, True, False, True]
    raw = simulate_recording(labels, quality=1.0, seed=2, sfreq=SFREQ, lead_in_s=2.5)
    save_untrained_classifier(client, raw.ch_names[:-1], "full", SFREQ)
    name = f"bgrl-app-{time.monotonic_ns()}"
    settings = client.app.state.service.settings
    settings.lsl_timeout_s = 0.5
    missing = client.post("/live", json={"classifier_id": "full", "stream_name": "nope"})
    settings.lsl_timeout_s = 5.0
    assert missing.status_code == 422
    assert missing.json() == {
        "detail": "no LSL stream named 'nope' within 0.5 s",
        "field": "stream_name",
    }
    player = lsl.replay(raw, name=name, chunk_size=32)
    publisher = None
    try:
        response = client.post("/live", json={"classifier_id": "full", "stream_name": name})
        assert response.status_code == 200, response.text
        assert response.json()["source"] == "lsl"
        ingest = client.app.state.service.live.ingest
        deadline = time.monotonic() + raw.times[-1] + 5.0
        triggers = []
        while len(triggers) < 2 and time.monotonic() < deadline:
            triggers += ingest.pop_triggers()
            time.sleep(0.05)
        marker = {"session_id": "s", "step": 1, "episode": 0, "action": 1}
        settings.epoch_wait_s = 10.0  # the window ends 0.8 s after the trigger (a loaded
        # machine delays the replayed stream by seconds; the answer comes once it is there)
        feedback = client.post(
            "/live/markers", json={**marker, "timestamp": triggers[-1].timestamp}
        )
        assert feedback.status_code == 200
        assert feedback.json()["status"] == "ok", feedback.json()["reason"]
        assert feedback.json()["synthetic"] is False  # the plumbing classifier is not marked

        # Markers from the sim's LSL marker stream are classified as they arrive.
        publisher = MarkerPublisher("bgrl-test-markers", name=f"{name}-markers")
        if not (
            resolve_streams(timeout=2.0, name=publisher.name)
            and resolve_streams(timeout=2.0, name=name)
        ):
            pytest.skip(
                "liblsl resolves only one outlet per process with this LSL config; add "
                "'[lab] KnownPeers = {127.0.0.1}' to services/core/lsl_loopback.cfg"
            )
        body = {"classifier_id": "full", "stream_name": name, "marker_stream": publisher.name}
        response = client.post("/live", json=body)
        assert response.status_code == 200, response.text
        assert response.json()["marker_stream"] == publisher.name
        ingest = client.app.state.service.live.ingest
        while ingest.latest_timestamp is None and time.monotonic() < deadline:
            time.sleep(0.05)
        start = ingest.latest_timestamp
        # the window ends 2 s after the newest sample the service had: wait longer than that
        # for it, so late chunks on a loaded machine do not fail the test
        settings.epoch_wait_s = 5.0
        with client.websocket_connect("/live/feedback") as ws:
            publisher.publish(ActionMarker(**{**marker, "step": 7, "timestamp": start + 1.2}))
            message = ws.receive_json()
        assert message["step"] == 7 and message["status"] == "ok", message["reason"]
    finally:
        if publisher is not None:
            publisher.close()
        client.delete("/live")
        player.stop()
    assert client.get("/live").json()["connected"] is False
