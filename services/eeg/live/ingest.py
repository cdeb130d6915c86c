"""Live EEG ingest: chunks from LSL or a websocket, integrity checks, epochs on demand.

:class:`LiveIngest` receives sample chunks with timestamps on the LSL clock (the clock of the
sim's action markers), checks every chunk against the previous one and feeds clean data to
the decoding side's :class:`~services.eeg.signal.preprocessing.OnlinePreprocessor`. It detects:

* **dropped samples / gaps**: the first timestamp of a chunk is later than the expected
  next sample by more than ``gap_tolerance_samples`` sample periods (a short loss up to
  ``max_dropped_s`` is reported as dropped samples, a longer one as a gap);
* **clock jumps**: timestamps go backwards, or jump forwards by more than the wall-clock
  time that passed between the two chunks plus ``clock_jump_s``;
* **disconnects**: :meth:`LiveIngest.mark_disconnected` (LSL stream lost, websocket closed)
  or no data for ``stale_after_s`` (checked by :meth:`LiveIngest.check_stale`); data that
  resume with the next expected timestamp were only late: the issue is closed and nothing
  is marked bad;
* **bad samples**: NaN or infinite values in a chunk.

Each problem is recorded as a :class:`StreamIssue` (the last :data:`MAX_ISSUES` are kept,
older ones are counted in ``issues_dropped``) and as a bad interval of the clock; the
preprocessing restarts in a new segment (the previous segments stay available for late
epoch requests), so no filter state crosses a break, and the ``settle_s`` after every
(re)start is bad too (the causal band-pass needs time to settle). :meth:`LiveIngest.epoch_for`
rejects an epoch whose window overlaps a bad interval, with the reason, and never returns
it as if it were clean.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass
from typing import Literal

import numpy as np

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR
from services.eeg.recordings.conventions import STIM_CHANNEL, TRIGGER_MASK
from services.eeg.signal.preprocessing import (
    EpochUnavailableError,
    OnlinePreprocessor,
    PreprocessingParams,
)

MAX_SEGMENTS = 3
"""Preprocessing segments kept (the current one and the two before the last breaks)."""
MAX_ISSUES = 100
"""Stream issues kept; older ones are dropped and counted (``LiveIngest.issues_dropped``)."""
MAX_BAD_INTERVALS = 1000
"""Bad intervals of the clock kept (far more than the buffer can hold epochs for)."""
IssueKind = Literal[
    "dropped_samples", "gap", "clock_jump", "disconnect", "bad_samples", "bad_marker"
]
EpochStatus = Literal["ok", "pending", "rejected"]


@dataclass(frozen=True)
class StreamIssue:
    """A detected problem in the incoming stream (times on the stream clock, s).

    ``bad_marker`` (a marker that could not be parsed) does not make data bad; every other
    kind does.
    """

    kind: IssueKind
    start: float
    end: float
    detail: str


@dataclass(frozen=True)
class EpochResult:
    """The answer to :meth:`LiveIngest.epoch_for`.

    Attributes
    ----------
    onset : float
        The action onset asked for (stream clock, s).
    status : {"ok", "pending", "rejected"}
        ``ok``: ``epoch`` holds clean preprocessed data; ``pending``: the window is not
        complete yet (ask again later); ``rejected``: it never will be, see ``reason``.
    epoch : ndarray, shape (n_channels, n_times_epoch) | None
        Preprocessed epoch (volts, float32) when ``status == "ok"``.
    reason : str | None
        Why the epoch is pending or rejected.
    """

    onset: float
    status: EpochStatus
    epoch: np.ndarray | None = None
    reason: str | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class Trigger:
    """An action trigger found in the stream's ``Status`` channel."""

    timestamp: float
    code: int


class LiveIngest:
    """Integrity-checked live ingest of one EEG stream, answering epoch requests.

    Parameters
    ----------
    stream_ch_names : sequence of str
        Channel names of the incoming samples, in column order (may include ``Status`` and
        channels the classifier does not use).
    sfreq : float
        Nominal sampling rate of the stream (Hz).
    eeg_ch_names : sequence of str | None
        Channels passed to the preprocessor, in this order (default: every stream channel
        except ``Status``). Must all be in ``stream_ch_names``.
    params : PreprocessingParams | None
        Preprocessing parameters (default: the paper's).
    buffer_s : float
        Seconds of preprocessed data kept.
    gap_tolerance_samples : float
        Largest accepted deviation of a chunk's first timestamp from the expected one, in
        sample periods.
    max_dropped_s : float
        Losses up to this long are reported as ``dropped_samples``, longer ones as ``gap``.
    clock_jump_s : float
        A forward timestamp jump exceeding the elapsed wall-clock time by more than this is
        a clock jump.
    settle_s : float
        Time after every (re)start during which data are bad (filter settling).
    stale_after_s : float
        :meth:`check_stale` reports a disconnect after this long without data.
    clock : callable
        Wall clock (s) used for arrival times; ``time.monotonic`` by default.
    """

    def __init__(
        self,
        stream_ch_names: Sequence[str],
        sfreq: float,
        *,
        eeg_ch_names: Sequence[str] | None = None,
        params: PreprocessingParams | None = None,
        buffer_s: float = 30.0,
        gap_tolerance_samples: float = 1.5,
        max_dropped_s: float = 0.1,
        clock_jump_s: float = 1.0,
        settle_s: float = 1.0,
        stale_after_s: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.stream_ch_names = list(stream_ch_names)
        if not math.isfinite(sfreq) or sfreq <= 0:
            raise ValueError(f"sfreq must be positive, got {sfreq}")
        self.sfreq = float(sfreq)
        if eeg_ch_names is None:
            eeg_ch_names = [ch for ch in self.stream_ch_names if ch != STIM_CHANNEL]
        missing = [ch for ch in eeg_ch_names if ch not in self.stream_ch_names]
        if missing:
            raise ValueError(f"stream lacks channels {', '.join(missing)}")
        self.eeg_ch_names = list(eeg_ch_names)
        self._picks = np.array([self.stream_ch_names.index(ch) for ch in self.eeg_ch_names])
        self._status_index = (
            self.stream_ch_names.index(STIM_CHANNEL)
            if STIM_CHANNEL in self.stream_ch_names
            else None
        )
        self._buffer_s = buffer_s
        self.params = params or PreprocessingParams()
        self._segments: deque[tuple[float, OnlinePreprocessor]] = deque(maxlen=MAX_SEGMENTS)
        self._segments.append((-math.inf, self._new_preprocessor()))
        self.gap_tolerance_s = gap_tolerance_samples / self.sfreq
        self.max_dropped_s = max_dropped_s
        self.clock_jump_s = clock_jump_s
        self.settle_s = settle_s
        self.stale_after_s = stale_after_s
        self._clock = clock
        self._lock = threading.Lock()
        self._arrived = threading.Condition()
        self._generation = 0
        """Counts ingested chunks and disconnects: :meth:`wait_epoch` sleeps until it moves."""
        self._issues: deque[StreamIssue] = deque(maxlen=MAX_ISSUES)
        self.issues_dropped = 0
        self._open_disconnect: StreamIssue | None = None
        self._bad: deque[tuple[float, float, str]] = deque(maxlen=MAX_BAD_INTERVALS)
        self._triggers: deque[Trigger] = deque(maxlen=10000)
        self._last_ts: float | None = None
        self._last_arrival: float | None = None
        self._last_status = 0
        self._listeners: list[Callable[[np.ndarray, np.ndarray], None]] = []
        self._disconnected_at: float | None = None
        self._bad_since: float | None = None
        self.n_samples = 0

    def _new_preprocessor(self) -> OnlinePreprocessor:
        return OnlinePreprocessor(
            self.eeg_ch_names, self.sfreq, self.params, buffer_s=self._buffer_s
        )

    @property
    def preprocessor(self) -> OnlinePreprocessor:
        """The preprocessor of the current segment (since the last restart)."""
        return self._segments[-1][1]

    # ------------------------------------------------------------------ input
    def push_chunk(
        self,
        samples: np.ndarray,
        timestamps: np.ndarray | None = None,
        *,
        first_timestamp: float | None = None,
    ) -> None:
        """Check and ingest one chunk.

        Parameters
        ----------
        samples : ndarray, shape (n_times, n_stream_channels)
            Samples in ``stream_ch_names`` order (EEG in volts).
        timestamps : ndarray, shape (n_times,) | None
            Per-sample timestamps (LSL). Discontinuities inside a chunk are detected too.
        first_timestamp : float | None
            Timestamp of ``samples[0]`` when per-sample timestamps are not given (websocket
            devices); the others are implied by the nominal rate.
        """
        samples = np.asarray(samples, dtype=np.float64)
        if samples.ndim != 2 or samples.shape[1] != len(self.stream_ch_names):
            raise ValueError(
                f"expected samples of shape (n_times, {len(self.stream_ch_names)}), "
                f"got {samples.shape}"
            )
        n = samples.shape[0]
        if n == 0:
            return
        if timestamps is None:
            if first_timestamp is None or not math.isfinite(first_timestamp):
                raise ValueError("give timestamps or a finite first_timestamp")
            timestamps = first_timestamp + np.arange(n) / self.sfreq
        timestamps = np.asarray(timestamps, dtype=np.float64)
        if timestamps.shape != (n,) or not np.all(np.isfinite(timestamps)):
            raise ValueError(f"timestamps must be {n} finite values")
        arrival = self._clock()
        with self._lock:
            # Split the chunk wherever its own timestamps are discontinuous.
            steps = np.diff(timestamps) - 1.0 / self.sfreq
            cuts = np.flatnonzero(np.abs(steps) > self.gap_tolerance_s) + 1
            for part_x, part_t in zip(
                np.split(samples, cuts), np.split(timestamps, cuts), strict=True
            ):
                self._ingest(part_x, part_t, arrival)
            self._last_arrival = arrival
        self._wake()
        for listener in list(self._listeners):
            listener(samples, timestamps)

    def _wake(self) -> None:
        with self._arrived:
            self._generation += 1
            self._arrived.notify_all()

    def add_listener(self, listener: Callable[[np.ndarray, np.ndarray], None]) -> None:
        """Call ``listener(samples, timestamps)`` with every chunk after it was checked
        (e.g. a live recorder; it must not raise)."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Callable[[np.ndarray, np.ndarray], None]) -> None:
        with suppress(ValueError):
            self._listeners.remove(listener)

    def _ingest(self, x: np.ndarray, t: np.ndarray, arrival: float) -> None:
        period = 1.0 / self.sfreq
        if self._last_ts is None:
            self._restart(t[0], None)
        else:
            expected = self._last_ts + period
            delta = t[0] - expected
            if self._disconnected_at is not None:
                # Data resuming exactly where they stopped were late, not lost (a stall, or
                # an accelerated source between pushes): the filters carry on.
                lost = abs(delta) > self.gap_tolerance_s
                self._close_disconnect(t[0], bad=lost)
                if lost:
                    self._restart(t[0], self._last_ts)
            elif delta < -self.gap_tolerance_s:
                self._issue(
                    "clock_jump", t[0], self._last_ts, f"timestamps went back by {-delta:.4f} s"
                )
                self._restart(t[0], None)
            elif delta > self.gap_tolerance_s:
                waited = arrival - (
                    self._last_arrival if self._last_arrival is not None else arrival
                )
                if delta > waited + self.clock_jump_s:
                    self._issue(
                        "clock_jump",
                        self._last_ts,
                        t[0],
                        f"timestamps jumped {delta:.3f} s ahead in {waited:.3f} s of wall time",
                    )
                elif delta <= self.max_dropped_s:
                    lost = round(delta * self.sfreq)
                    self._issue("dropped_samples", self._last_ts, t[0], f"{lost} samples missing")
                else:
                    self._issue("gap", self._last_ts, t[0], f"no data for {delta:.3f} s")
                self._restart(t[0], self._last_ts)
        self._disconnected_at = None
        self._last_ts = float(t[-1])
        self.n_samples += x.shape[0]

        finite = np.all(np.isfinite(x[:, self._picks]), axis=1)
        if finite.all() and self._bad_since is None:
            self._feed(x, t)
            return
        # Feed the clean runs only; the filter restarts after every bad run.
        edges = np.flatnonzero(np.diff(np.r_[0, finite.astype(int), 0]))
        previous_stop = 0
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            if start > previous_stop and self._bad_since is None:
                self._bad_since = float(t[previous_stop])
            if self._bad_since is not None:
                self._issue(
                    "bad_samples",
                    self._bad_since,
                    float(t[start]),
                    "NaN or infinite values in the samples",
                )
                self._restart(float(t[start]), self._bad_since)
                self._bad_since = None
            self._feed(x[start:stop], t[start:stop])
            previous_stop = stop
        if previous_stop < x.shape[0] and self._bad_since is None:
            self._bad_since = float(t[previous_stop])

    def _feed(self, x: np.ndarray, t: np.ndarray) -> None:
        self.preprocessor.push(x[:, self._picks], float(t[0]))
        if self._status_index is not None:
            codes = np.rint(x[:, self._status_index]).astype(np.int64) & TRIGGER_MASK
            previous = np.r_[self._last_status, codes[:-1]]
            for i in np.flatnonzero(
                (codes != previous) & np.isin(codes, (TRIGGER_CORRECT, TRIGGER_ERROR))
            ):
                self._triggers.append(Trigger(float(t[i]), int(codes[i])))
            self._last_status = int(codes[-1])

    @property
    def issues(self) -> list[StreamIssue]:
        """The last :data:`MAX_ISSUES` detected problems, oldest first."""
        with self._lock:
            return list(self._issues)

    def _add_issue(self, issue: StreamIssue) -> None:
        if len(self._issues) == self._issues.maxlen:
            self.issues_dropped += 1
        self._issues.append(issue)

    def _close_disconnect(self, resumed_at: float, *, bad: bool = True) -> None:
        """Close the open disconnect issue at ``resumed_at``; mark the outage bad if
        ``bad`` (samples were lost)."""
        issue = self._open_disconnect
        if issue is None:
            return
        self._open_disconnect = None
        closed = StreamIssue("disconnect", issue.start, resumed_at, issue.detail)
        for i in range(len(self._issues) - 1, -1, -1):
            if self._issues[i] is issue:  # still kept (not dropped)
                self._issues[i] = closed
                break
        if bad:
            self._bad.append((issue.start, resumed_at, f"disconnect: {issue.detail}"))

    def _restart(self, first_ts: float, bad_from: float | None) -> None:
        """Start a new preprocessing segment; data from ``bad_from`` until settled are bad."""
        if self.preprocessor.n_buffered:
            self._segments.append((first_ts, self._new_preprocessor()))
        else:
            self.preprocessor.reset()
        start = first_ts if bad_from is None else bad_from
        self._bad.append((start, first_ts + self.settle_s, "filter settling after (re)start"))

    def _issue(self, kind: IssueKind, start: float, end: float, detail: str) -> None:
        self._add_issue(StreamIssue(kind, start, end, detail))
        self._bad.append((start, end, f"{kind.replace('_', ' ')}: {detail}"))

    def report_bad_marker(self, timestamp: float, detail: str) -> None:
        """Record a marker that could not be used (the EEG data stay good)."""
        with self._lock:
            self._add_issue(StreamIssue("bad_marker", timestamp, timestamp, detail))

    def mark_disconnected(self, detail: str = "stream disconnected") -> None:
        """Record that the source went away (LSL stream lost, websocket closed)."""
        with self._lock:
            if self._disconnected_at is None and self._last_ts is not None:
                self._disconnected_at = self._last_ts
                self._open_disconnect = StreamIssue("disconnect", self._last_ts, math.inf, detail)
                self._add_issue(self._open_disconnect)
        self._wake()

    def check_stale(self) -> bool:
        """Mark a disconnect when no data arrived for ``stale_after_s``; True if disconnected."""
        with self._lock:
            last = self._last_arrival
        if last is not None and self._clock() - last > self.stale_after_s:
            self.mark_disconnected(f"no data for more than {self.stale_after_s:g} s")
        return self.disconnected

    @property
    def disconnected(self) -> bool:
        return self._disconnected_at is not None

    @property
    def latest_timestamp(self) -> float | None:
        """Timestamp of the newest sample received (stream clock)."""
        return self._last_ts

    def pop_triggers(self) -> list[Trigger]:
        """Action triggers seen in the ``Status`` channel since the last call."""
        with self._lock:
            out = list(self._triggers)
            self._triggers.clear()
        return out

    # ----------------------------------------------------------------- output
    def epoch_for(self, onset: float) -> EpochResult:
        """The preprocessed epoch after an action onset, or why there is none (yet).

        Parameters
        ----------
        onset : float
            Action onset on the stream clock (the marker's LSL timestamp).
        """
        p = self.params
        start, end = onset + p.tmin, onset + p.tmax
        with self._lock:
            for bad_start, bad_end, reason in self._bad:
                if bad_start < end and bad_end > start:
                    return EpochResult(
                        onset,
                        "rejected",
                        reason=f"window {start:.3f}-{end:.3f} s overlaps bad data ({reason})",
                    )
            if self._bad_since is not None and self._bad_since < end:
                return EpochResult(
                    onset,
                    "rejected",
                    reason=f"window {start:.3f}-{end:.3f} s overlaps bad data "
                    f"(NaN or infinite values since {self._bad_since:.3f} s)",
                )
            if self._last_ts is None:
                return EpochResult(onset, "pending", reason="no data received yet")
            if self._last_ts < end:
                if self._disconnected_at is not None:
                    return EpochResult(
                        onset, "rejected", reason="stream disconnected before the window ended"
                    )
                return EpochResult(onset, "pending", reason="window not complete yet")
            segment = self.preprocessor
            for segment_start, preprocessor in self._segments:
                if segment_start <= start:
                    segment = preprocessor
            try:
                epoch = segment.epoch_at(onset)
            except EpochUnavailableError as exc:
                return EpochResult(onset, "rejected", reason=str(exc))
        if epoch is None:
            return EpochResult(onset, "pending", reason="window not complete yet")
        return EpochResult(onset, "ok", epoch=epoch)

    def wait_epoch(
        self,
        onset: float,
        *,
        timeout_s: float = 2.0,
        poll_s: float = 0.05,
        stop: threading.Event | None = None,
    ) -> EpochResult:
        """Wait until :meth:`epoch_for` is not pending or ``timeout_s`` passes.

        The wait sleeps until the next chunk (or disconnect) arrives, so the epoch is
        answered as soon as its last sample is ingested; ``poll_s`` bounds each sleep (how
        soon ``stop`` is noticed). ``stop`` (optional) ends the wait early with a rejection
        (the source is closing).
        """
        deadline = time.monotonic() + timeout_s
        while True:
            with self._arrived:
                generation = self._generation
            result = self.epoch_for(onset)
            if result.status != "pending":
                return result
            if stop is not None and stop.is_set():
                return EpochResult(onset, "rejected", reason="the live source was closed")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.check_stale()
                return EpochResult(
                    onset, "rejected", reason=f"no complete window within {timeout_s:g} s"
                )
            with self._arrived:
                if self._generation == generation:  # nothing arrived since epoch_for looked
                    self._arrived.wait(timeout=min(poll_s, remaining))
