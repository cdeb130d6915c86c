"""A rig's channel map reaches the EEG service when a live session reads the rig's LSL stream."""

from __future__ import annotations

from typing import Any

import pytest

from services.worker import live_eeg
from services.worker.live_eeg import EegDecoder


class RecordingCalls:
    """Stands in for the EEG service's client: keeps every call."""

    base_url = "http://eeg.invalid"

    def __init__(self) -> None:
        self.calls: list[tuple[str, str, dict[str, Any]]] = []

    def call(
        self, method: str, path: str, *, json: dict[str, Any], idempotent: bool = False
    ) -> dict[str, Any]:
        assert idempotent, f"{method} {path} is retried by attach, so it must be idempotent"
        self.calls.append((method, path, json))
        return {}


@pytest.mark.parametrize(
    ("channel_map", "sent"),
    [({"A1": "Fp1", "B32": "Cz"}, {"A1": "Fp1", "B32": "Cz"}), (None, None)],
)
def test_the_lsl_attach_carries_the_rigs_channel_map(
    monkeypatch: pytest.MonkeyPatch, channel_map: dict[str, str] | None, sent: Any
) -> None:
    monkeypatch.setattr(live_eeg, "WARMUP_S", 0.0)
    eeg = RecordingCalls()
    decoder = EegDecoder(
        eeg,  # type: ignore[arg-type]
        "c1",
        source=None,
        accelerated=False,
        stream_name="BrainNav-EEG",
        retry_s=0.0,
        period_s=1.5,
        channel_map=channel_map,
    )
    decoder.attach()
    assert len(eeg.calls) == 1
    method, path, body = eeg.calls[0]
    assert (method, path, body["stream_name"]) == ("POST", "/live", "BrainNav-EEG")
    assert body.get("channel_map") == sent
