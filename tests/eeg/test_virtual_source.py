"""The virtual subject as a live source: deterministic continuous generation, responses
driven by action markers, the accelerated ingest driver and marker/epoch alignment."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from services.core.markers import ActionMarker
from services.eeg.decoding.classifier import ErrPClassifier
from services.eeg.decoding.eegnet import EEGNet
from services.eeg.recordings.conventions import SYNTHETIC_TAG
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from services.eeg.signal.preprocessing import PreprocessingParams
from services.eeg.virtual.ingest import IngestError, VirtualIngestClient
from services.eeg.virtual.source import VirtualEEGSource
from services.eeg.virtual.subject import SyntheticRecording

SFREQ = 256.0
EEG = ["Fz", "FC1", "FCz", "FC2", "C3", "Cz", "C4", "Pz"]
WITHOUT_FCZ = ["Fz", "FC1", "FC2", "C3", "Cz", "C4", "Pz", "Oz"]
"""A cap the platform accepts, but not for a classifier trained with FCz."""
CLASSIFIER = "plumbing"
PERIOD_S = 1.5


def _marker(step: int, correct: bool | None, t0: float = 1.0) -> ActionMarker:
    return ActionMarker(
        session_id="s",
        step=step,
        episode=0,
        action=0,
        correct=correct,
        timestamp=t0 + step * PERIOD_S,
    )


class AsgiConnection:
    """The ASGI test client's websocket as an :class:`IngestConnection`."""

    def __init__(self, session) -> None:
        self._session = session

    def send(self, message: str | bytes) -> None:
        if isinstance(message, bytes):
            self._session.send_bytes(message)
        else:
            self._session.send_text(message)

    def recv(self) -> str:
        return self._session.receive_text()

    def close(self) -> None:
        self._session.close()


def save_untrained_classifier(
    client: TestClient, ch_names: list[str], classifier_id: str, sfreq: float = SFREQ
) -> None:
    """An untrained classifier of ``sfreq`` input stored as the service stores them (enough
    for plumbing)."""
    torch.manual_seed(0)
    params = PreprocessingParams()
    model = EEGNet(len(ch_names), 2, params.n_times_epoch)
    clf = ErrPClassifier(model, params, ch_names, sfreq, 1e5, {"test_accuracy": 0.5})
    clf.save(client.app.state.service.classifiers.folder / classifier_id)


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(EEGSettings(data_dir=tmp_path, epoch_wait_s=0.5))) as c:
        save_untrained_classifier(c, EEG, CLASSIFIER)
        yield c


def test_generation_is_continuous_deterministic_and_independent_of_chunking():
    markers = [_marker(i, correct=i % 3 != 0) for i in range(8)]
    one = VirtualEEGSource(quality=0.5, seed=3, sfreq=SFREQ)
    for m in markers:
        one.add_marker(m)
    whole, first = one.generate_until(45.0)  # crosses two background segments
    assert first == 0.0
    assert whole.shape == (int(45.0 * SFREQ), 65)
    assert whole.dtype == np.float32
    two = VirtualEEGSource(quality=0.5, seed=3, sfreq=SFREQ)
    for m in markers:
        two.add_marker(m)
    parts, t = [], 0.0
    for step in np.random.default_rng(0).uniform(0.001, 4.0, size=1000):
        t = min(t + step, 45.0)
        samples, first = two.generate_until(t)
        assert first == pytest.approx(sum(len(p) for p in parts) / SFREQ)
        parts.append(samples)
        if t == 45.0:
            break
    np.testing.assert_array_equal(np.concatenate(parts), whole)
    # No seam at the cross-fades: the sample-to-sample step stays as large as elsewhere.
    steps = np.abs(np.diff(whole[:, :-1], axis=0)).max(axis=1)
    for seam in (20.0, 21.0, 40.0, 41.0):
        i = int(seam * SFREQ)
        assert steps[i - 3 : i + 3].max() < 4 * np.median(steps)
    # Status: the marker's trigger code at its own sample, 10 ms long (3 samples at 256 Hz).
    status = whole[:, -1]
    onsets = np.flatnonzero(np.diff(np.r_[0.0, status]) > 0)
    assert onsets.tolist() == [round(m.timestamp * SFREQ) for m in markers]
    assert status[onsets].tolist() == [m.trigger for m in markers]
    assert int(np.sum(status > 0)) == 3 * len(markers)
    assert one.description.startswith(SYNTHETIC_TAG)


def test_same_subject_as_the_offline_generator_and_errp_only_after_errors():
    offline = SyntheticRecording([True], quality=0.4, seed=11, sfreq=SFREQ)
    live = VirtualEEGSource(quality=0.4, seed=11, sfreq=SFREQ)
    shift = offline.info["description"].split("shift=")[1]
    assert f"shift={live.latency_shift_s:+.3f}s" == f"shift={shift}"
    # Same seed, different quality: the difference is the label-dependent response only.
    sources = {
        q: VirtualEEGSource(quality=q, seed=5, sfreq=SFREQ, channels=["FCz"]) for q in (0.0, 1.0)
    }
    markers = [_marker(0, correct=False), _marker(1, correct=True), _marker(2, correct=None)]
    for source in sources.values():
        for m in markers:
            source.add_marker(m)
    data = {q: s.generate_until(6.0)[0][:, 0].astype(np.float64) for q, s in sources.items()}
    diff = data[1.0] - data[0.0]
    windows = [
        diff[round(m.timestamp * SFREQ) : round((m.timestamp + 1.0) * SFREQ)] for m in markers
    ]
    error_peak, correct_peak, unknown_peak = (float(np.abs(w).max()) for w in windows)
    assert error_peak > 5e-6  # an ErrP at FCz, several microvolts
    assert correct_peak < error_peak / 2
    assert unknown_peak < 1e-9  # no label: no label-dependent response
    assert float(np.abs(diff[: round(1.0 * SFREQ)]).max()) < 1e-9  # nothing before the action


def test_a_late_marker_is_counted_and_its_response_cut():
    source = VirtualEEGSource(quality=0.5, seed=0, sfreq=SFREQ)
    source.generate_until(2.0)
    source.add_marker(_marker(0, correct=False, t0=1.9))
    assert source.late_markers == 1
    assert source.n_markers == 1


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="quality"):
        VirtualEEGSource(quality=1.5, seed=0)
    with pytest.raises(ValueError, match="sfreq"):
        VirtualEEGSource(quality=0.5, seed=0, sfreq=128.0)
    with pytest.raises(ValueError, match="unknown"):
        VirtualEEGSource(quality=0.5, seed=0, channels=["FCz", "NotAChannel"])


def _run_accelerated(
    client: TestClient, source: VirtualEEGSource, markers: list[ActionMarker], *, decode: bool
):
    """Push ``source`` through WS /live/ingest; the epochs the service cuts at the markers,
    the feedback of ``POST /live/markers`` (when ``decode``) and the stream's triggers."""
    epochs, feedback = [], []
    with client.websocket_connect(f"/live/ingest?classifier_id={CLASSIFIER}") as ws:
        ingest_client = VirtualIngestClient(source, AsgiConnection(ws))
        for m in markers:
            ingest_client.push_epoch(m)
            if decode:
                response = client.post("/live/markers", json=m.model_dump(mode="json"))
                assert response.status_code == 200
                feedback.append(response.json())
            result = client.app.state.service.live.ingest.epoch_for(m.timestamp)
            assert result.status == "ok", result.reason
            epochs.append(result.epoch)
        triggers = client.app.state.service.live.ingest.pop_triggers()
        assert client.app.state.service.live.synthetic is True
    return epochs, feedback, triggers


def test_accelerated_ingest_decodes_every_marker_through_the_live_path(client):
    source = VirtualEEGSource(quality=0.6, seed=2, sfreq=SFREQ, channels=EEG)
    markers = [_marker(i, correct=i % 2 == 0, t0=2.0) for i in range(6)]
    _, feedback, triggers = _run_accelerated(client, source, markers, decode=True)
    assert [f["status"] for f in feedback] == ["ok"] * 6
    assert [f["step"] for f in feedback] == list(range(6))
    assert all(f["synthetic"] is False for f in feedback)  # the (real-data) classifier's flag
    # Every trigger in the stream's Status channel sits on its marker's sample.
    assert [t.code for t in triggers] == [m.trigger for m in markers]
    for trigger, m in zip(triggers, markers, strict=True):
        assert abs(trigger.timestamp - m.timestamp) <= 0.5 / SFREQ
    # Samples go up to each marker's epoch end, nothing beyond (no wall-clock pacing).
    assert source.n_generated == round((markers[-1].timestamp + 0.8) * SFREQ) + 2


def test_ingest_refusal_is_raised_with_the_reason(client):
    source = VirtualEEGSource(quality=0.5, seed=0, sfreq=SFREQ, channels=WITHOUT_FCZ)
    url = f"/live/ingest?classifier_id={CLASSIFIER}"
    with client.websocket_connect(url) as ws, pytest.raises(IngestError, match="FCz"):
        VirtualIngestClient(source, AsgiConnection(ws))


def test_injected_latency_is_recovered_by_marker_epoch_alignment_within_one_sample(client):
    """The subject's ErrP shift is found again in the live epochs cut at the markers.

    Three subjects with the same seed (hence the same background and trial jitter): no ErrP
    (quality 0), and quality 1 with ErrP latency shifts of 0 and 62.5 ms (8 samples at the
    features' 128 Hz). Subtracting the quality-0 epochs leaves the preprocessed ErrP; the lag
    maximising the cross-correlation of the two subjects' mean error-trial waves is the
    injected latency.
    """
    markers = [_marker(i, correct=i % 2 == 0, t0=2.0) for i in range(24)]
    waves = {}
    for name, quality, shift in (("none", 0.0, 0.0), ("early", 1.0, 0.0), ("late", 1.0, 0.0625)):
        source = VirtualEEGSource(
            quality=quality, seed=4, sfreq=SFREQ, channels=EEG, latency_shift_s=shift
        )
        epochs, _, _ = _run_accelerated(client, source, markers, decode=False)
        waves[name] = np.stack(epochs)[[not m.correct for m in markers], EEG.index("FCz")]
    early = (waves["early"] - waves["none"]).mean(axis=0)
    late = (waves["late"] - waves["none"]).mean(axis=0)
    lags = np.arange(-20, 21)
    n = early.size
    scores = [
        np.dot(early[max(0, -k) : n - max(0, k)], late[max(0, k) : n - max(0, -k)]) for k in lags
    ]
    recovered_s = lags[int(np.argmax(scores))] / 128.0
    assert abs(recovered_s - 0.0625) <= 1 / 128.0


def test_a_pause_between_accelerated_pushes_is_reported_but_loses_no_epoch(client):
    """No data for longer than ``stale_after_s`` shows as a disconnect; data resuming at the
    next expected timestamp close it without marking anything bad (nothing was lost)."""
    source = VirtualEEGSource(quality=0.5, seed=3, sfreq=SFREQ, channels=EEG)
    markers = [_marker(i, correct=True, t0=2.0) for i in range(3)]
    with client.websocket_connect(f"/live/ingest?classifier_id={CLASSIFIER}") as ws:
        ingest_client = VirtualIngestClient(source, AsgiConnection(ws))
        ingest = client.app.state.service.live.ingest
        ingest.stale_after_s = 0.05
        ingest_client.push_epoch(markers[0])
        time.sleep(0.2)  # the runner is busy elsewhere
        status = client.get("/live").json()
        assert status["connected"] is False
        assert [i["kind"] for i in status["issues"]] == ["disconnect"]
        ingest_client.push_epoch(markers[1])
        ingest_client.push_epoch(markers[2])
        status = client.get("/live").json()
        assert status["connected"] is True
        assert status["issues"][0]["end"] is not None
        results = [ingest.epoch_for(m.timestamp) for m in markers]
        assert [r.status for r in results] == ["ok", "ok", "ok"], [r.reason for r in results]
