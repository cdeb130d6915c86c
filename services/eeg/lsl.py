"""LSL on loopback or the lab network: replay recordings, ingest EEG and action markers.

* :func:`replay` streams a recording (BDF/EDF/FIF file or a Raw, e.g. a virtual subject's)
  in real time with ``mne_lsl.player.PlayerLSL``, ``Status`` channel included.
* :class:`LslEegIngest` connects an ``mne_lsl.stream.StreamLSL`` to a
  :class:`~services.eeg.live.LiveIngest`: every acquired chunk, with its per-sample LSL
  timestamps (clock-synchronised, not de-jittered, so gaps stay visible), goes through
  the integrity checks.
* :class:`MarkerInlet` reads :class:`~services.core.markers.ActionMarker` objects from the
  sim's marker stream; marker timestamps and EEG timestamps are both on the LSL clock.

Set ``LSLAPICFG`` to ``services/core/lsl_loopback.cfg`` to keep streams on this machine.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import mne
import numpy as np
from mne_lsl.lsl import StreamInlet, local_clock, resolve_streams
from mne_lsl.player import PlayerLSL
from mne_lsl.stream import StreamLSL

from services.core.markers import MARKER_STREAM_NAME, MARKER_STREAM_TYPE, ActionMarker
from services.eeg.live import LiveIngest
from services.eeg.preprocessing import PreprocessingParams

EEG_STREAM_NAME = "BrainNav-EEG"
EEG_STREAM_TYPE = "EEG"

__all__ = [
    "EEG_STREAM_NAME",
    "LslEegIngest",
    "MarkerInlet",
    "lsl_clock",
    "replay",
]


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
    return player.start()


class LslEegIngest:
    """An LSL EEG inlet feeding a :class:`LiveIngest`.

    Parameters
    ----------
    name : str
        Name of the EEG stream to connect to.
    eeg_ch_names : sequence of str | None
        Channels given to the preprocessor (default: every channel except ``Status``).
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
    """

    def __init__(
        self,
        name: str = EEG_STREAM_NAME,
        *,
        eeg_ch_names: Sequence[str] | None = None,
        params: PreprocessingParams | None = None,
        timeout: float = 5.0,
        bufsize: float = 5.0,
        **ingest_kwargs,
    ) -> None:
        self.stream = StreamLSL(bufsize, name=name)
        try:
            self.stream.connect(
                acquisition_delay=0.001, processing_flags=["clocksync"], timeout=timeout
            )
        except RuntimeError as exc:
            raise RuntimeError(f"no LSL stream named {name!r} within {timeout:g} s") from exc
        self.ingest = LiveIngest(
            self.stream.ch_names,
            self.stream.info["sfreq"],
            eeg_ch_names=eeg_ch_names,
            params=params,
            **ingest_kwargs,
        )
        self.stream.add_callback(self._on_chunk)

    def _on_chunk(
        self, data: np.ndarray, timestamps: np.ndarray, info
    ) -> tuple[np.ndarray, np.ndarray]:
        self.ingest.push_chunk(data, timestamps)
        return data, timestamps

    def close(self) -> None:
        """Disconnect from the stream and report the disconnect to the ingest."""
        if self.stream.connected:
            self.stream.disconnect()
        self.ingest.mark_disconnected("LSL inlet closed")

    def __enter__(self) -> LslEegIngest:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        # resolve_streams stops at the first stream of any name, so ask until the deadline.
        deadline = time.monotonic() + timeout
        infos: list = []
        while not infos and time.monotonic() < deadline:
            infos = [
                info
                for info in resolve_streams(timeout=min(0.5, timeout), name=name)
                if info.name == name and info.stype == MARKER_STREAM_TYPE
            ]
        if not infos:
            raise RuntimeError(f"no LSL marker stream named {name!r} within {timeout:g} s")
        self._inlet = StreamInlet(infos[0], processing_flags=["clocksync"])
        self._inlet.open_stream(timeout=timeout)

    def pull(self, timeout: float = 0.0) -> list[ActionMarker]:
        """Markers received since the last call (malformed ones raise ``ValueError``)."""
        samples, _ = self._inlet.pull_chunk(timeout=timeout)
        return [ActionMarker.from_lsl(sample[0]) for sample in samples]

    def close(self) -> None:
        self._inlet.close_stream()
