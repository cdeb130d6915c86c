"""Live ingest: integrity checks, epoch rejection, LSL loopback replay."""

from __future__ import annotations

import time

import numpy as np
import pytest

from services.eeg.live.ingest import MAX_ISSUES, LiveIngest
from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.epochs import epochs_from_raw
from services.eeg.virtual.subject import simulate_recording

SFREQ = 512.0
CHANNELS = ["FCz", "Cz", "Pz", STIM_CHANNEL]


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def _noise(n: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(0.0, 20e-6, size=(n, len(CHANNELS)))
    x[:, -1] = 0.0
    return x


def _feed(ingest: LiveIngest, clock: FakeClock, t0: float, seconds: float, chunk: int = 64):
    """Push ``seconds`` of noise in chunks starting at stream time ``t0``, advancing the clock."""
    n = int(seconds * SFREQ)
    x = _noise(n, seed=int(t0 * 10))
    for i in range(0, n, chunk):
        part = x[i : i + chunk]
        ingest.push_chunk(part, first_timestamp=t0 + i / SFREQ)
        clock.now += part.shape[0] / SFREQ


def _ingest() -> tuple[LiveIngest, FakeClock]:
    clock = FakeClock()
    return LiveIngest(CHANNELS, SFREQ, clock=clock, settle_s=1.0), clock


def test_clean_stream_gives_epochs_and_pending_before_window_ends():
    ingest, clock = _ingest()
    _feed(ingest, clock, 100.0, 3.0)
    assert ingest.issues == []
    result = ingest.epoch_for(101.5)
    assert result.ok, result.reason
    assert result.epoch.shape == (3, ingest.params.n_times_epoch)
    assert ingest.epoch_for(102.5).status == "pending"
    early = ingest.epoch_for(100.5)  # inside the filter-settling second
    assert early.status == "rejected" and "settling" in early.reason


def test_dropped_samples_gap_and_rejection_reason():
    ingest, clock = _ingest()
    _feed(ingest, clock, 0.0, 3.0)
    _feed(ingest, clock, 3.0 + 10 / SFREQ, 4.0)  # 10 samples lost
    clock.now += 2.0
    _feed(ingest, clock, 9.0, 4.0)  # ~2 s without data (wall time passed: not a clock jump)
    kinds = [issue.kind for issue in ingest.issues]
    assert kinds == ["dropped_samples", "gap"]
    assert "10 samples missing" in ingest.issues[0].detail
    rejected = ingest.epoch_for(2.6)
    assert rejected.status == "rejected"
    assert "dropped samples" in rejected.reason
    assert ingest.epoch_for(4.5).ok  # settled again after the drop, before the gap
    gap = ingest.epoch_for(6.8)
    assert gap.status == "rejected" and "gap" in gap.reason
    assert ingest.epoch_for(10.5).ok


def test_clock_jumps_backwards_and_forwards():
    ingest, clock = _ingest()
    _feed(ingest, clock, 50.0, 2.0)
    _feed(ingest, clock, 49.0, 2.0)  # timestamps went back
    _feed(ingest, clock, 200.0, 2.0)  # 149 s ahead after a few ms of wall time
    assert [issue.kind for issue in ingest.issues] == ["clock_jump", "clock_jump"]
    assert "went back" in ingest.issues[0].detail
    assert "ahead" in ingest.issues[1].detail


def test_disconnect_by_staleness_and_resume():
    ingest, clock = _ingest()
    _feed(ingest, clock, 0.0, 2.0)
    assert not ingest.check_stale()
    clock.now += 5.0
    assert ingest.check_stale()
    pending = ingest.epoch_for(1.6)
    assert pending.status == "rejected" and "disconnected" in pending.reason
    _feed(ingest, clock, 7.0, 3.0)
    assert not ingest.disconnected
    (issue,) = ingest.issues
    assert issue.kind == "disconnect" and issue.end == pytest.approx(7.0)
    assert ingest.epoch_for(8.2).ok


def test_nan_samples_are_rejected_not_classified():
    ingest, clock = _ingest()
    _feed(ingest, clock, 0.0, 2.0)
    bad = _noise(64)
    bad[10:20, 1] = np.nan
    ingest.push_chunk(bad, first_timestamp=2.0)
    clock.now += 64 / SFREQ
    _feed(ingest, clock, 2.0 + 64 / SFREQ, 3.0)
    assert [issue.kind for issue in ingest.issues] == ["bad_samples"]
    result = ingest.epoch_for(1.5)
    assert result.status == "rejected" and "bad samples" in result.reason
    assert ingest.epoch_for(3.5).ok


def test_issues_are_bounded_and_an_outage_is_bad_even_after_its_issue_was_dropped():
    ingest, clock = _ingest()
    x = _noise(32)
    t = 0.0
    for _ in range(MAX_ISSUES + 20):  # 10 samples lost before every chunk after the first
        ingest.push_chunk(x, first_timestamp=t)
        clock.now += 0.1
        t += (len(x) + 10) / SFREQ
    kept = ingest.issues
    assert len(kept) == MAX_ISSUES and ingest.issues_dropped == 19
    assert {issue.kind for issue in kept} == {"dropped_samples"}
    assert kept[0].start == pytest.approx((19 * 42 + 31) / SFREQ)  # the 20th drop is the oldest
    _feed(ingest, clock, t, 3.0)
    ingest.mark_disconnected("cable")
    for _ in range(MAX_ISSUES):  # push the open disconnect out of the kept issues
        ingest.report_bad_marker(t, "not a marker")
    assert "disconnect" not in {issue.kind for issue in ingest.issues}
    clock.now += 5.0
    _feed(ingest, clock, t + 8.0, 3.0)
    outage = ingest.epoch_for(t + 4.0)
    assert outage.status == "rejected" and "disconnect: cable" in outage.reason
    assert ingest.epoch_for(t + 9.5).ok  # bad markers do not make data bad


def test_status_triggers_and_bad_input():
    ingest, _clock = _ingest()
    x = _noise(1024)
    x[300:305, -1] = 2
    x[800:805, -1] = 1 + 0xFF00  # BioSemi flags in the upper bits are masked off
    ingest.push_chunk(x, first_timestamp=10.0)
    triggers = ingest.pop_triggers()
    assert [(round(t.timestamp - 10.0, 4), t.code) for t in triggers] == [
        (round(300 / SFREQ, 4), 2),
        (round(800 / SFREQ, 4), 1),
    ]
    with pytest.raises(ValueError, match="shape"):
        ingest.push_chunk(np.zeros((4, 3)), first_timestamp=20.0)
    with pytest.raises(ValueError, match="first_timestamp"):
        ingest.push_chunk(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="lacks channels"):
        LiveIngest(CHANNELS, SFREQ, eeg_ch_names=["Oz"])


def test_chunked_live_epochs_equal_offline_epochs():
    """Same recording, fed in chunks through LiveIngest, gives the offline epochs."""
    labels = [True, False, True, False, False]
    raw = simulate_recording(labels, quality=1.0, seed=4, sfreq=SFREQ)
    offline = epochs_from_raw(raw)
    ingest = LiveIngest(raw.ch_names, SFREQ, settle_s=0.0)
    data = raw.get_data().T
    t0 = 1000.0
    for i in range(0, data.shape[0], 37):
        ingest.push_chunk(data[i : i + 37], first_timestamp=t0 + i / SFREQ)
    triggers = ingest.pop_triggers()
    assert [t.code for t in triggers] == [1 if ok else 2 for ok in labels]
    live = np.stack([ingest.epoch_for(t.timestamp).epoch for t in triggers])
    np.testing.assert_allclose(live, offline.X, atol=1e-9)


@pytest.mark.lsl
def test_lsl_loopback_replay_yields_clean_epochs():
    lsl = pytest.importorskip("services.eeg.live.lsl")
    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    labels = [True, False, False, True, False, True]
    raw = simulate_recording(labels, quality=1.0, seed=6, sfreq=SFREQ, lead_in_s=2.5)
    name = f"bgrl-test-{time.monotonic_ns()}"
    player = lsl.replay(raw, name=name, chunk_size=32)
    try:
        with lsl.LslEegIngest(name, timeout=5.0, settle_s=1.0) as source:
            ingest = source.ingest
            deadline = time.monotonic() + raw.times[-1] + 5.0
            triggers = []
            while len(triggers) < len(labels) and time.monotonic() < deadline:
                triggers += ingest.pop_triggers()
                time.sleep(0.05)
            results = [ingest.wait_epoch(t.timestamp, timeout_s=2.0) for t in triggers]
    finally:
        player.stop()
    assert len(triggers) >= len(labels) - 1  # the first may pass before the inlet connects
    assert [t.code for t in triggers] == [1 if ok else 2 for ok in labels][-len(triggers) :]
    assert ingest.issues == [] or all(i.kind == "disconnect" for i in ingest.issues)
    assert all(r.ok for r in results[1:]), [r.reason for r in results]
    assert results[-1].epoch.shape == (64, ingest.params.n_times_epoch)


def test_rational_rate_stream_gives_the_offline_epochs():
    """A 250 Hz 8-channel stream (OpenBCI-like) through the integrity-checked ingest."""
    from tests.eeg.caps import CAP_8, LABELS, virtual_recording

    raw = virtual_recording(250.0, CAP_8, seed=9)
    offline = epochs_from_raw(raw)
    ingest = LiveIngest(raw.ch_names, 250.0, settle_s=1.0)
    assert ingest.eeg_ch_names == CAP_8
    data = raw.get_data()
    for start in range(0, raw.n_times, 25):
        part = data[:, start : start + 25].T
        ingest.push_chunk(part, first_timestamp=300.0 + start / 250.0)
    triggers = ingest.pop_triggers()
    assert [t.code for t in triggers] == [1 if ok else 2 for ok in LABELS]
    live = np.stack([ingest.epoch_for(t.timestamp).epoch for t in triggers])
    np.testing.assert_allclose(live, offline.X, atol=1e-9)


@pytest.mark.lsl
def test_lsl_stream_with_device_names_needs_the_rig_map():
    lsl = pytest.importorskip("services.eeg.live.lsl")
    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    from tests.eeg.caps import CAP_8, virtual_recording

    raw = virtual_recording(500.0, CAP_8, seed=3)
    device = {ch: f"E{i + 1}" for i, ch in enumerate(CAP_8)}
    raw.rename_channels({**device, STIM_CHANNEL: "TRIG"})
    rig_map = {**{dev: std for std, dev in device.items()}, "TRIG": "Status"}
    name = f"bgrl-test-map-{time.monotonic_ns()}"
    player = lsl.replay(raw, name=name, chunk_size=25)
    try:
        with pytest.raises(ValueError, match=r"EEG stream '.*': 0 channels with standard"):
            lsl.LslEegIngest(name, timeout=5.0)
        with pytest.raises(
            ValueError, match=r"the channel map names channels the source does not have: E9"
        ):
            lsl.LslEegIngest(name, channel_map={**rig_map, "E9": "Oz"}, timeout=5.0)
        wrong = {**rig_map, "E6": "Oz"}  # Cz wired to the wrong site: Cz is missing
        with pytest.raises(ValueError, match=r"missing the fronto-central sites .*: Cz \("):
            lsl.LslEegIngest(name, channel_map=wrong, timeout=5.0)
        with lsl.LslEegIngest(name, channel_map=rig_map, timeout=5.0) as source:
            assert source.ingest.eeg_ch_names == CAP_8
            assert source.ingest.stream_ch_names == [*CAP_8, STIM_CHANNEL]
            deadline = time.monotonic() + 5.0
            while source.ingest.n_samples < 500 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert source.ingest.n_samples >= 500
    finally:
        player.stop()


@pytest.mark.lsl
def test_post_live_takes_the_rig_channel_map(tmp_path):
    """POST /live refuses a device-named stream with the reason and takes it with its map."""
    from fastapi.testclient import TestClient

    from services.eeg.service.app import create_app
    from services.eeg.service.settings import EEGSettings

    lsl = pytest.importorskip("services.eeg.live.lsl")
    try:
        lsl.lsl_clock()
    except Exception as exc:  # liblsl missing or unusable on this machine
        pytest.skip(f"liblsl cannot run here: {exc}")
    from tests.eeg.caps import CAP_8, virtual_recording

    raw = virtual_recording(500.0, CAP_8, seed=4)
    raw.rename_channels({ch: f"E{i + 1}" for i, ch in enumerate(CAP_8)})
    rig_map = {f"E{i + 1}": ch for i, ch in enumerate(CAP_8)}
    name = f"bgrl-app-map-{time.monotonic_ns()}"
    player = lsl.replay(raw, name=name, chunk_size=25)
    settings = EEGSettings(data_dir=tmp_path, lsl_timeout_s=5.0)
    try:
        with TestClient(create_app(settings)) as client:
            bad = client.post("/live", json={"stream_name": name, "channel_map": {"E1": ""}})
            assert bad.status_code == 422
            assert bad.json()["message"] == (
                "channel_map.E1: String should have at least 1 character"
            )
            refused = client.post("/live", json={"stream_name": name})
            assert refused.status_code == 422
            assert refused.json() == {
                "detail": f"EEG stream {name!r}: 0 channels with standard 10-20/10-10 names; "
                "8 to 256 are needed (give the rig a channel map when the amplifier names "
                "its channels otherwise)",
                "field": "stream_name",
            }
            mapped = client.post("/live", json={"stream_name": name, "channel_map": rig_map})
            assert mapped.status_code == 200, mapped.text
            assert client.app.state.service.live.ingest.eeg_ch_names == CAP_8
    finally:
        player.stop()
