"""The LSL marker stream of executed actions, so that EEG recordings carry them.

One irregular-rate string stream named :data:`~services.core.markers.MARKER_STREAM_NAME`
(type :data:`~services.core.markers.MARKER_STREAM_TYPE`), one channel; each sample is
:meth:`ActionMarker.to_lsl` (JSON) pushed with the marker's own LSL timestamp, so that a
recorder (LabRecorder, ``mne_lsl``) places it exactly when the action was shown.
"""

from __future__ import annotations

import threading

from mne_lsl.lsl import StreamInfo, StreamOutlet, local_clock

from services.core.markers import MARKER_STREAM_NAME, MARKER_STREAM_TYPE, ActionMarker

__all__ = ["MarkerPublisher", "lsl_clock"]


def lsl_clock() -> float:
    """Current time on the LSL clock (s), the time base of every marker."""
    return local_clock()


class MarkerPublisher:
    """Publishes :class:`ActionMarker` objects on an LSL outlet.

    Parameters
    ----------
    source_id
        Stable LSL ``source_id`` so recorders can re-attach after a restart.
    name
        Stream name; the EEG service looks for :data:`MARKER_STREAM_NAME`.

    The outlet is thread-safe to use through :meth:`publish` (sessions step from several
    worker threads). Call :meth:`close` to withdraw the stream.
    """

    def __init__(self, source_id: str, *, name: str = MARKER_STREAM_NAME) -> None:
        self.name = name
        self.source_id = source_id
        info = StreamInfo(
            name=name,
            stype=MARKER_STREAM_TYPE,
            n_channels=1,
            sfreq=0.0,
            dtype="string",
            source_id=self.source_id,
        )
        self._outlet: StreamOutlet | None = StreamOutlet(info)
        self._lock = threading.Lock()
        self.n_published = 0

    def publish(self, marker: ActionMarker) -> None:
        """Push one marker, time-stamped with ``marker.timestamp`` (LSL clock)."""
        with self._lock:
            if self._outlet is None:
                raise RuntimeError(f"marker stream {self.name!r} is closed")
            self._outlet.push_sample([marker.to_lsl()], timestamp=marker.timestamp)
            self.n_published += 1

    @property
    def has_consumers(self) -> bool:
        """True while at least one inlet (recorder) is connected."""
        with self._lock:
            return self._outlet is not None and self._outlet.has_consumers

    def close(self) -> None:
        """Withdraw the stream; later :meth:`publish` calls raise ``RuntimeError``."""
        with self._lock:
            self._outlet = None
