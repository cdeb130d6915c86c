"""The virtual subject streaming over LSL in real time (loopback): markers from an LSL
marker stream drive it, the EEG service follows it, reports a stream drop and recovers when
it comes back, and refuses a stream without the classifier's channels. A few seconds each."""

from __future__ import annotations

import time
import uuid

import numpy as np
import pytest
from fastapi.testclient import TestClient
from mne_lsl.lsl import StreamInfo, StreamOutlet, local_clock

from services.core.markers import MARKER_STREAM_TYPE, ActionMarker
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.virtual.stream import VirtualLslStream
from tests.eeg.test_virtual_source import (
    CLASSIFIER,
    EEG,
    SFREQ,
    WITHOUT_FCZ,
    save_untrained_classifier,
)


def _wait(condition, timeout_s: float, what: str, state=None) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}: {state() if state else ''}")
        time.sleep(0.05)


@pytest.fixture
def client(tmp_path):
    settings = EEGSettings(data_dir=tmp_path, epoch_wait_s=2.0, lsl_timeout_s=3.0)
    with TestClient(create_app(settings)) as c:
        save_untrained_classifier(c, EEG, CLASSIFIER)
        yield c


@pytest.fixture
def names():
    tag = uuid.uuid4().hex[:8]
    return f"test-virtual-eeg-{tag}", f"test-markers-{tag}"


def _marker_outlet(name: str) -> StreamOutlet:
    info = StreamInfo(name, MARKER_STREAM_TYPE, 1, 0.0, "string", f"{name}-source")
    return StreamOutlet(info)


def test_markers_drive_the_live_subject_and_a_drop_is_reported_and_recovered(client, names):
    eeg_name, marker_name = names
    marker_outlet = _marker_outlet(marker_name)
    with VirtualLslStream(
        quality=0.8,
        seed=1,
        sfreq=SFREQ,
        channels=EEG,
        name=eeg_name,
        marker_stream=marker_name,
        lag_s=0.5,  # generous: the test machine may be busy
    ) as stream:
        response = client.post("/live", json={"classifier_id": CLASSIFIER, "stream_name": eeg_name})
        assert response.status_code == 200, response.text
        _wait(lambda: client.get("/live").json()["n_samples"] > 0, 5.0, "EEG samples")
        assert stream.following_markers.wait(15.0)
        sent = []
        for step, correct in enumerate((False, True)):
            marker = ActionMarker(
                session_id="rt",
                step=step,
                episode=0,
                action=1,
                correct=correct,
                timestamp=local_clock(),
            )
            marker_outlet.push_sample([marker.to_lsl()], marker.timestamp)
            sent.append(marker)
            time.sleep(0.3)
        _wait(lambda: stream.markers_received == 2, 3.0, "markers at the subject")
        assert client.app.state.service.live.synthetic is True  # from the LSL description
        ingest = client.app.state.service.live.ingest
        triggers: list = []
        _wait(lambda: len(triggers.__iadd__(ingest.pop_triggers())) == 2, 3.0, "Status triggers")
        # Each marker's trigger is on the sample the marker's timestamp names (same clock).
        assert [t.code for t in triggers] == [2, 1]
        for trigger, marker in zip(triggers, sent, strict=True):
            assert abs(trigger.timestamp - marker.timestamp) <= 1.0 / SFREQ
        assert stream.source.late_markers == 0
        assert client.get("/live").json()["connected"] is True

        stream.drop()
        _wait(lambda: client.get("/live").json()["connected"] is False, 5.0, "the drop")
        issues = client.get("/live").json()["issues"]
        assert [i["kind"] for i in issues] == ["disconnect"]
        assert issues[0]["end"] is None  # still going on
        stream.resume()
        _wait(
            lambda: client.get("/live").json()["connected"] is True,
            30.0,  # liblsl re-resolves the source id: seconds on a busy machine
            "recovery",
            lambda: client.get("/live").json(),
        )
        status = client.get("/live").json()
        outage = [i for i in status["issues"] if i["kind"] == "disconnect"]
        assert len(outage) == 1 and outage[0]["end"] is not None
        assert outage[0]["end"] - outage[0]["start"] >= 0.5
        assert status["error"] is None


def test_a_stream_without_the_classifiers_channels_is_refused_with_the_reason(client, names):
    eeg_name, _ = names
    with VirtualLslStream(
        quality=0.5, seed=0, sfreq=SFREQ, channels=WITHOUT_FCZ, name=eeg_name, marker_stream=None
    ):
        response = client.post("/live", json={"classifier_id": CLASSIFIER, "stream_name": eeg_name})
    assert response.status_code == 422
    body = response.json()
    assert body["field"] == "stream_name"
    assert "FCz" in body["detail"]
    assert client.get("/live").json()["connected"] is False


def test_the_stream_is_marked_synthetic_and_follows_the_lsl_clock(names):
    from mne_lsl.lsl import StreamInlet, resolve_streams

    from services.eeg.live.lsl import stream_is_synthetic

    eeg_name, _ = names
    with VirtualLslStream(
        quality=0.5, seed=0, sfreq=SFREQ, channels=EEG, name=eeg_name, marker_stream=None
    ):
        infos = [i for i in resolve_streams(timeout=3.0, name=eeg_name) if i.name == eeg_name]
        assert len(infos) == 1
        inlet = StreamInlet(infos[0])
        inlet.open_stream(timeout=3.0)
        assert stream_is_synthetic(inlet.get_sinfo())
        assert inlet.get_sinfo().get_channel_names() == [*EEG, "Status"]
        time.sleep(0.5)
        _, stamps = inlet.pull_chunk(timeout=1.0)
        inlet.close_stream()
    assert len(stamps) > 0
    np.testing.assert_allclose(np.diff(stamps), 1.0 / SFREQ, atol=1e-6)
    # About lag_s behind the LSL clock, like an amplifier's buffer.
    assert 0.0 < local_clock() - stamps[-1] < 2.0


def test_bgrl_subject_stream_without_a_file_streams_the_live_subject(names):
    from typer.testing import CliRunner

    from services.cli.main import app

    eeg_name, marker_name = names
    result = CliRunner().invoke(
        app,
        [
            "subject",
            "stream",
            "--quality",
            "0.7",
            "--seed",
            "3",
            "--name",
            eeg_name,
            "--marker-stream",
            marker_name,
            "--duration",
            "1",
        ],
    )
    assert result.exit_code == 0, result.output
    assert (
        f"streaming the virtual subject (SYNTHETIC, quality 0.7, seed 3, 256 Hz) as LSL stream "
        f"{eeg_name!r}, following markers of {marker_name!r}" in result.output
    )
    stopped = result.output.strip().splitlines()[-1]
    assert stopped.startswith("stopped: ") and stopped.endswith(" samples, 0 markers")
    assert int(stopped.split()[1]) > 128  # about 1 s minus the lag at 256 Hz
