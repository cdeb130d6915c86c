"""LSL on loopback or the lab network: replay recordings, ingest EEG and action markers.

* :func:`replay` streams a recording (BDF/EDF/FIF file or a Raw, e.g. a virtual subject's)
  in real time with ``mne_lsl.player.PlayerLSL``, ``Status`` channel included.
* :class:`LslEegIngest` connects an ``mne_lsl.stream.StreamLSL`` to a
  :class:`~services.eeg.live.ingest.LiveIngest`: every acquired chunk, with its per-sample LSL
  timestamps (clock-synchronised, not de-jittered, so gaps stay visible), goes through
  the integrity checks.
* :class:`MarkerInlet` reads :class:`~services.core.markers.ActionMarker` objects from the
  sim's marker stream, one at a time (a malformed marker is returned as a
  :class:`RejectedMarker` with the reason, the rest of its chunk is kept); marker
  timestamps and EEG timestamps are both on the LSL clock.

Both release their LSL inlet on every path: a constructor that fails closes what it opened.

Set ``LSLAPICFG`` to ``services/core/lsl_loopback.cfg`` to keep streams on this machine.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping, Sequence
from contextlib import suppress
from dataclasses import dataclass, field
from pathlib import Path

import mne
import numpy as np
from mne_lsl.lsl import StreamInfo, StreamInlet, local_clock, resolve_streams
from mne_lsl.player import PlayerLSL
from mne_lsl.stream import StreamLSL
from pydantic import ValidationError

from services.core.markers import MARKER_STREAM_NAME, MARKER_STREAM_TYPE, ActionMarker
from services.eeg.live.ingest import LiveIngest
from services.eeg.recordings.channels import resolve_channels
from services.eeg.recordings.conventions import SYNTHETIC_ELEMENT
from services.eeg.signal.preprocessing import PreprocessingParams

EEG_STREAM_NAME = "BrainNav-EEG"
EEG_STREAM_TYPE = "EEG"

__all__ = [
    "EEG_STREAM_NAME",
    "LslEegIngest",
    "MarkerInlet",
    "PulledMarkers",
    "RejectedMarker",
    "lsl_clock",
    "replay",
    "stream_is_synthetic",
]

logger = logging.getLogger(__name__)


def stream_is_synthetic(sinfo: StreamInfo) -> bool:
    """Whether an LSL stream's description marks its data as generated."""
    return not sinfo.desc.child(SYNTHETIC_ELEMENT).empty()


def lsl_clock() -> float:
    """Current LSL time (s): the clock of EEG samples and action markers."""
    return local_clock()


def replay(
    recording: str | Path | mne.io.BaseRaw,
    *,
    name: str = EEG_STREAM_NAME,
    chunk_size: int = 64,
    n_repeat: int = 1,
    source_id: str = "bgrl-replay",
) -> PlayerLSL:
    """Start streaming a recording over LSL in real time; call ``.stop()`` when done.

    Parameters
    ----------
    recording : str | Path | mne.io.BaseRaw
        The recording to replay (all channels, ``Status`` included).
    name : str
        LSL stream name.
    chunk_size : int
        Samples per pushed chunk (64 at 2048 Hz: one chunk every 31 ms).
    n_repeat : int
        How many times the recording is played.
    source_id : str
        LSL source id.
    """
    player = PlayerLSL(
        recording if isinstance(recording, mne.io.BaseRaw) else str(recording),
        chunk_size=chunk_size,
        n_repeat=n_repeat,
        name=name,
        source_id=source_id,
        annotations=False,
    )
    try:
        return player.start()
    except BaseException:
        with suppress(Exception):  # release whatever start() had opened
            player.stop()
        raise


class LslEegIngest:
    """An LSL EEG inlet feeding a :class:`LiveIngest`.

    Parameters
    ----------
    name : str
        Name of the EEG stream to connect to.
    eeg_ch_names : sequence of str | None
        Channels (standard names) given to the preprocessor, e.g. a classifier's
        (default: every EEG channel of the stream).
    channel_map : mapping | None
        The rig's ``{device_name: standard_name}`` (a target may be ``Status``); channels
        it does not list are read as standard 10-20/10-10 names, case-insensitively
        (:func:`services.eeg.recordings.channels.resolve_channels`).
    params : PreprocessingParams | None
        Preprocessing parameters (e.g. a classifier's).
    timeout : float
        Seconds to wait for the stream to appear.
    bufsize : float
        Seconds kept in the ``StreamLSL`` buffer (the ingest keeps its own).
    **ingest_kwargs
        Passed to :class:`LiveIngest`.

    Raises
    ------
    RuntimeError
        If no stream named ``name`` appears within ``timeout``.
    ValueError
        If the stream's channels do not fit (a mapped channel missing, too few EEG
        channels, the ErrP's sites or a classifier's channels missing) or its rate cannot
        be resampled; the message names them and the inlet is closed again.

    A chunk the ingest cannot take stops the ingest: :attr:`error` names the problem (it is
    logged once), and so does a stream whose acquisition stopped by itself.
    """

    def __init__(
        self,
        name: str = EEG_STREAM_NAME,
        *,
        eeg_ch_names: Sequence[str] | None = None,
        channel_map: Mapping[str, str] | None = None,
        params: PreprocessingParams | None = None,
        timeout: float = 5.0,
        bufsize: float = 5.0,
        **ingest_kwargs,
    ) -> None:
        self.name = name
        self._failure: str | None = None
        self._closed = threading.Event()
        self.stream = StreamLSL(bufsize, name=name)
        try:
            self.stream.connect(
                acquisition_delay=0.001, processing_flags=["clocksync"], timeout=timeout
            )
        except RuntimeError as exc:
            raise RuntimeError(f"no LSL stream named {name!r} within {timeout:g} s") from exc
        try:
            channels = resolve_channels(
                self.stream.ch_names, channel_map, source=f"EEG stream {name!r}"
            )
            self.channels = channels
            self.ingest = LiveIngest(
                channels.names,
                self.stream.info["sfreq"],
                eeg_ch_names=channels.eeg if eeg_ch_names is None else eeg_ch_names,
                params=params,
                **ingest_kwargs,
            )
            self.stream.add_callback(self._on_chunk)
        except BaseException:
            self._disconnect()
            raise

    def _on_chunk(
        self, data: np.ndarray, timestamps: np.ndarray, info
    ) -> tuple[np.ndarray, np.ndarray]:
        if self._failure is None:
            try:
                self.ingest.push_chunk(data, timestamps)
            except Exception as exc:
                self._failure = f"EEG stream {self.name!r}: {type(exc).__name__}: {exc}"
                logger.exception("LSL ingest of %r stopped", self.name)
                self.ingest.mark_disconnected(self._failure)
        return data, timestamps

    @property
    def synthetic(self) -> bool:
        """The stream's description marks its data as generated (a virtual subject)."""
        return stream_is_synthetic(self.stream.sinfo)

    @property
    def error(self) -> str | None:
        """Why the ingest stopped receiving data, or None while it works (or was closed)."""
        if self._failure is not None:
            return self._failure
        if not self._closed.is_set() and not self.stream.connected:
            return f"EEG stream {self.name!r}: LSL acquisition stopped (see the log)"
        return None

    def _disconnect(self) -> None:
        if self.stream.connected:
            self.stream.disconnect()

    def close(self) -> None:
        """Disconnect from the stream and report the disconnect to the ingest."""
        self._closed.set()
        try:
            self._disconnect()
        finally:
            self.ingest.mark_disconnected("LSL inlet closed")

    def __enter__(self) -> LslEegIngest:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class RejectedMarker:
    """A marker sample that is not a valid :class:`ActionMarker`."""

    timestamp: float
    """LSL time the sample was sent."""
    reason: str


@dataclass
class PulledMarkers:
    """What one :meth:`MarkerInlet.pull` received: valid markers and rejected samples."""

    markers: list[ActionMarker] = field(default_factory=list)
    rejected: list[RejectedMarker] = field(default_factory=list)


class MarkerInlet:
    """Reads the sim's :class:`ActionMarker` stream.

    Parameters
    ----------
    name : str
        Marker stream name.
    timeout : float
        Seconds to wait for the stream to appear.
    """

    def __init__(self, name: str = MARKER_STREAM_NAME, *, timeout: float = 5.0) -> None:
        # resolve_streams stops at the first stream of any name, so ask until the deadline,
        # each wait twice the last: liblsl answers a unicast query (a KnownPeers host on
        # another network) after at least its UnicastMinRTT (0.75 s), so a short first
        # wait finds a local stream at once and a later one gives a remote peer its time.
        deadline = time.monotonic() + timeout
        infos: list = []
        wait_s = 0.5
        while not infos and (remaining := deadline - time.monotonic()) > 0:
            infos = [
                info
                for info in resolve_streams(timeout=min(wait_s, remaining), name=name)
                if info.name == name and info.stype == MARKER_STREAM_TYPE
            ]
            wait_s *= 2
        if not infos:
            raise RuntimeError(f"no LSL marker stream named {name!r} within {timeout:g} s")
        self._inlet = StreamInlet(infos[0], processing_flags=["clocksync"])
        try:
            self._inlet.open_stream(timeout=timeout)
            # The first clock-offset estimate takes ~0.6 s: get it now, not on the first marker.
            self._inlet.time_correction(timeout=timeout)
        except BaseException:
            self.close()
            raise

    def pull(self, timeout: float = 0.0) -> PulledMarkers:
        """Markers received since the last call, each parsed on its own.

        A malformed sample is returned in ``rejected`` with the reason; it does not affect
        the other markers of the chunk.
        """
        samples, timestamps = self._inlet.pull_chunk(timeout=timeout)
        pulled = PulledMarkers()
        for sample, timestamp in zip(samples, timestamps, strict=True):
            try:
                pulled.markers.append(ActionMarker.from_lsl(sample[0]))
            except ValidationError as exc:
                problems = "; ".join(
                    f"{'.'.join(str(p) for p in err['loc']) or 'marker'}: {err['msg']}"
                    for err in exc.errors()
                )
                pulled.rejected.append(
                    RejectedMarker(float(timestamp), f"invalid action marker: {problems}")
                )
            except (ValueError, IndexError) as exc:
                pulled.rejected.append(RejectedMarker(float(timestamp), str(exc)))
        return pulled

    def close(self) -> None:
        """Close the inlet (safe to call more than once)."""
        with suppress(Exception):  # already closed or lost: nothing left to release
            self._inlet.close_stream()
