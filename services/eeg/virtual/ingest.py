"""The accelerated driver of the virtual subject: a :class:`VirtualEEGSource` pushed to the
EEG service's ``WS /live/ingest`` as fast as the service takes it.

:class:`VirtualIngestClient` has no wall-clock pacing: generated samples are sent with their
timestamps (binary chunks) up to each marker's epoch end, so a session runs as fast as
compute allows through the live decoding path (tests, ``bgrl demo --accelerated``,
benchmarks). The real-time driver is :class:`services.eeg.virtual.stream.VirtualLslStream`.
"""

from __future__ import annotations

import json
import struct
from typing import Any, Protocol

import numpy as np

from services.core.markers import ActionMarker
from services.eeg.virtual.source import VirtualEEGSource


class IngestConnection(Protocol):
    """A websocket connection to ``WS /live/ingest`` (text and binary messages)."""

    def send(self, message: str | bytes) -> None: ...

    def recv(self) -> str: ...

    def close(self) -> None: ...


class IngestError(RuntimeError):
    """The EEG service refused the ingest header or a chunk (the message says why)."""


class VirtualIngestClient:
    """Accelerated driver: pushes a :class:`VirtualEEGSource` to ``WS /live/ingest``.

    No wall-clock pacing: :meth:`push_until` generates and sends samples up to a time on the
    source's clock as fast as the service takes them. Use :meth:`connect` for a URL, or
    give any :class:`IngestConnection` (tests use the ASGI test client's).

    Parameters
    ----------
    source : VirtualEEGSource
        The subject; its markers are fed with :meth:`add_marker` or directly.
    connection : IngestConnection
        An open websocket to ``/live/ingest?classifier_id=...``; the header is sent here.
    chunk_s : float
        Longest chunk sent in one message (s).
    """

    def __init__(
        self, source: VirtualEEGSource, connection: IngestConnection, *, chunk_s: float = 0.5
    ) -> None:
        if not chunk_s > 0:
            raise ValueError(f"chunk_s must be positive, got {chunk_s}")
        self.source = source
        self._connection = connection
        self._chunk_s = chunk_s
        self.n_sent = 0
        header = {"ch_names": source.ch_names, "sfreq": source.sfreq, "synthetic": True}
        self._exchange(header)

    @classmethod
    def connect(
        cls,
        source: VirtualEEGSource,
        eeg_url: str,
        classifier_id: str | None,
        *,
        headers: dict[str, str] | None = None,
        chunk_s: float = 0.5,
        open_timeout_s: float = 10.0,
    ) -> VirtualIngestClient:
        """Open ``WS /live/ingest`` of the EEG service at ``eeg_url`` (``http://host:port``).

        ``classifier_id`` None: nothing is decoded, the stream can only be recorded
        (calibration). ``headers`` are sent with the handshake (e.g.
        ``{"X-Service-Token": token}``).
        """
        from urllib.parse import quote

        from websockets.sync.client import connect

        base = eeg_url.rstrip("/").replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        query = f"?classifier_id={quote(classifier_id)}" if classifier_id else ""
        url = f"{base}/live/ingest{query}"
        connection = connect(
            url, additional_headers=headers, open_timeout=open_timeout_s, max_size=None
        )
        try:
            return cls(source, connection, chunk_s=chunk_s)
        except BaseException:
            connection.close()
            raise

    def _exchange(self, message: dict[str, Any] | bytes) -> dict[str, Any]:
        self._connection.send(message if isinstance(message, bytes) else json.dumps(message))
        reply = json.loads(self._connection.recv())
        if not reply.get("ok"):
            raise IngestError(f"EEG ingest refused: {reply.get('error')}")
        return reply

    def add_marker(self, marker: ActionMarker) -> None:
        """Feed one action to the subject (before pushing past its onset)."""
        self.source.add_marker(marker)

    def push_until(self, timestamp: float) -> int:
        """Generate and send every sample before ``timestamp``; returns the samples sent."""
        sent = 0
        step = self._chunk_s
        while self.source.next_timestamp < timestamp - 0.5 / self.source.sfreq:
            samples, first = self.source.generate_until(
                min(timestamp, self.source.next_timestamp + step)
            )
            if not len(samples):
                break
            # Binary: the float32 samples as they are (JSON of 0.5 s of 65 channels costs
            # ~50 ms of CPU to write and parse; these bytes, well under 1 ms).
            self._exchange(struct.pack("<d", first) + np.asarray(samples, "<f4").tobytes())
            sent += len(samples)
        self.n_sent += sent
        return sent

    def push_epoch(self, marker: ActionMarker, *, epoch_end_s: float = 0.8) -> int:
        """Feed ``marker`` and send samples up to its epoch's end (plus two samples).

        After this the EEG service holds the whole [0, ``epoch_end_s``] window after the
        marker, so ``POST /live/markers`` decodes it without waiting.
        """
        self.add_marker(marker)
        return self.push_until(marker.timestamp + epoch_end_s + 2.0 / self.source.sfreq)

    def close(self) -> None:
        """Close the websocket (the EEG service records a disconnect)."""
        self._connection.close()

    def __enter__(self) -> VirtualIngestClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
