"""The virtual subject streaming over LSL in real time (``bgrl subject stream``).

:class:`VirtualLslStream` runs a :class:`~services.eeg.virtual.source.VirtualEEGSource` on
the LSL clock: one thread pushes its samples to an LSL outlet (type ``EEG``, the 64 BioSemi
channels or a subset, ``Status`` last) at wall-clock pace, ``lag_s`` behind real time like an
amplifier's buffer; another follows the sim's marker stream
(:data:`~services.core.markers.MARKER_STREAM_NAME`), so every executed action's oracle label
drives the subject (an ErrP after an error). A marker must arrive within ``lag_s`` of its
timestamp for its response to be whole; a later one is counted in ``late_markers``.

The stream is marked synthetic: its LSL description has a ``synthetic`` element holding the
source's ``SYNTHETIC ...`` description (:func:`services.eeg.live.lsl.stream_is_synthetic` reads
it), and the EEG
service carries the flag into its live recordings.

:meth:`VirtualLslStream.drop` stops the outlet (as a crashed amplifier app would) and
:meth:`VirtualLslStream.resume` brings it back under the same source id; the samples of the
outage are generated and discarded, so the stream resumes on time with a gap.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from contextlib import suppress

import mne
import numpy as np
from mne_lsl.lsl import StreamInfo, StreamOutlet

from services.core.markers import MARKER_STREAM_NAME
from services.eeg.live.lsl import EEG_STREAM_NAME, EEG_STREAM_TYPE, MarkerInlet, lsl_clock
from services.eeg.recordings.conventions import SYNTHETIC_ELEMENT
from services.eeg.virtual.source import DEFAULT_SFREQ, VirtualEEGSource

logger = logging.getLogger(__name__)

MARKER_POLL_S = 0.002
"""Marker stream polling period (s); a marker reaches the subject within a few ms."""
RECONNECT_S = 1.0
"""How long the marker thread waits for the marker stream before trying again."""


class VirtualLslStream:
    """The virtual subject as a real-time LSL EEG stream driven by the sim's markers.

    Parameters
    ----------
    quality, seed, sfreq, channels, latency_shift_s
        The subject (as :class:`~services.eeg.virtual.source.VirtualEEGSource`).
    name : str
        LSL stream name.
    marker_stream : str | None
        Name of the marker stream to follow; None: no markers (feed :attr:`source`).
    chunk_s : float
        Push period (s).
    lag_s : float
        How far behind the LSL clock samples are pushed (s); markers arriving later than
        this after their timestamp are cut.
    source_id : str
        LSL source id (an inlet recovers a stream with the same id after a drop).

    Call :meth:`start`, then :meth:`stop` (or use it as a context manager).
    """

    def __init__(
        self,
        *,
        quality: float,
        seed: int,
        sfreq: float = DEFAULT_SFREQ,
        channels: Sequence[str] | None = None,
        latency_shift_s: float | None = None,
        name: str = EEG_STREAM_NAME,
        marker_stream: str | None = MARKER_STREAM_NAME,
        chunk_s: float = 1 / 32,
        lag_s: float = 0.15,
        source_id: str = "bgrl-virtual-subject",
    ) -> None:
        if not (0 < chunk_s <= 1.0) or not (0 <= lag_s <= 5.0):
            raise ValueError(f"need 0 < chunk_s <= 1 and 0 <= lag_s <= 5, got {chunk_s}, {lag_s}")
        self.source = VirtualEEGSource(
            quality=quality,
            seed=seed,
            sfreq=sfreq,
            channels=channels,
            latency_shift_s=latency_shift_s,
            start_timestamp=lsl_clock(),
        )
        self.name = name
        self.marker_stream = marker_stream
        self.chunk_s = chunk_s
        self.lag_s = lag_s
        self.source_id = source_id
        self.n_pushed = 0
        self.markers_received = 0
        self.error: str | None = None
        """Why a background thread stopped, if one did."""
        self.following_markers = threading.Event()
        """Set once the marker stream is connected (and its clock offset known)."""
        self._stop = threading.Event()
        self._outlet_lock = threading.Lock()
        self._outlet: StreamOutlet | None = None
        self._threads: list[threading.Thread] = []

    # ------------------------------------------------------------ lifecycle
    def _make_outlet(self) -> StreamOutlet:
        source = self.source
        sinfo = StreamInfo(
            self.name,
            EEG_STREAM_TYPE,
            len(source.ch_names),
            source.sfreq,
            "float32",
            self.source_id,
        )
        info = mne.create_info(
            source.ch_names, source.sfreq, ["eeg"] * len(source.eeg_ch_names) + ["stim"]
        )
        sinfo.set_channel_info(info)
        sinfo.desc.append_child_value(SYNTHETIC_ELEMENT, source.description)
        return StreamOutlet(sinfo, chunk_size=max(1, round(self.chunk_s * source.sfreq)))

    def start(self) -> VirtualLslStream:
        """Open the outlet and start pushing (and following markers)."""
        self._outlet = self._make_outlet()
        self._threads = [threading.Thread(target=self._push_loop, name="virtual-eeg", daemon=True)]
        if self.marker_stream is not None:
            self._threads.append(
                threading.Thread(target=self._marker_loop, name="virtual-eeg-markers", daemon=True)
            )
        for thread in self._threads:
            thread.start()
        logger.info("virtual subject streaming as LSL %r (%s)", self.name, self.source.description)
        return self

    def stop(self) -> None:
        """Stop the threads and close the outlet (idempotent)."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        self.drop()

    def drop(self) -> None:
        """Close the outlet now (a stream drop); :meth:`resume` reopens it."""
        with self._outlet_lock:
            outlet, self._outlet = self._outlet, None
        if outlet is not None:
            outlet._del()  # destroy it now: inlets see the stream break off

    def resume(self) -> None:
        """Reopen the outlet after :meth:`drop` (same name and source id)."""
        with self._outlet_lock:
            if self._outlet is None:
                self._outlet = self._make_outlet()

    @property
    def streaming(self) -> bool:
        return self._outlet is not None and not self._stop.is_set()

    def __enter__(self) -> VirtualLslStream:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -------------------------------------------------------------- threads
    def _push_loop(self) -> None:
        source = self.source
        try:
            next_push = time.monotonic()
            while not self._stop.is_set():
                samples, first = source.generate_until(lsl_clock() - self.lag_s)
                with self._outlet_lock:
                    if self._outlet is not None and len(samples) == 1:
                        self._outlet.push_sample(samples[0], first)
                    elif self._outlet is not None and len(samples):
                        stamps = first + np.arange(len(samples)) / source.sfreq
                        self._outlet.push_chunk(np.ascontiguousarray(samples), stamps)
                    if self._outlet is not None:
                        self.n_pushed += len(samples)
                next_push += self.chunk_s
                self._stop.wait(max(0.0, next_push - time.monotonic()))
        except Exception as exc:
            logger.exception("virtual EEG stream %r stopped", self.name)
            self.error = f"{type(exc).__name__}: {exc}"

    def _marker_loop(self) -> None:
        assert self.marker_stream is not None
        inlet: MarkerInlet | None = None
        try:
            while not self._stop.is_set():
                if inlet is None:
                    try:
                        inlet = MarkerInlet(self.marker_stream, timeout=RECONNECT_S)
                        self.following_markers.set()
                        logger.info("following the marker stream %r", self.marker_stream)
                    except RuntimeError:
                        continue
                pulled = inlet.pull(timeout=0.0)
                for rejected in pulled.rejected:
                    logger.warning("ignoring a malformed marker: %s", rejected.reason)
                for marker in pulled.markers:
                    self.source.add_marker(marker)
                    self.markers_received += 1
                self._stop.wait(MARKER_POLL_S)
        except Exception as exc:
            logger.exception("marker stream %r stopped", self.marker_stream)
            self.error = f"marker stream: {type(exc).__name__}: {exc}"
        finally:
            if inlet is not None:
                with suppress(Exception):
                    inlet.close()
