"""24-bit BDF writing, in chunks, with an exact ``Status`` trigger channel.

``mne.export.export_raw(..., fmt="bdf")`` scales a stim channel by its physical range, after
which ``read_raw_bdf`` reads the Status codes wrong. We write the ``Status`` signal with a
physical range equal to the digital range (-8388608..8388607), so the codes round-trip
exactly. The header is edfio's, and so is the physical -> digital rule, so the bytes are
the ones edfio's whole-array writer gives; the samples are digitised and written a few
data records at a time.
"""

from __future__ import annotations

import datetime
import io
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol

import edfio
import mne
import numpy as np

from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_TAG

BDF_DIGITAL_RANGE = (-8388608, 8388607)
CHUNK_VALUES = 1 << 22
"""Values (channels x samples) per chunk when a recording is read or written (32 MB)."""
_EDF_FIELD_CHARS = 80


class GeneratedRecording(Protocol):
    """A recording made block by block as it is read (a virtual subject's
    :class:`~services.eeg.virtual.subject.SyntheticRecording`, a live recording's folder):
    its ``info`` and length, and its samples (all channels) in blocks from the start."""

    info: mne.Info
    n_times: int

    def iter_chunks(self) -> Iterator[tuple[int, np.ndarray]]:
        """(first sample, block (n_channels, k)) from the first sample to the last."""
        ...


def _edf_token(text: str, limit: int) -> str:
    """ASCII header token without spaces or ``=`` (MNE splits on it), at most ``limit`` chars."""
    clean = "".join(ch if 33 <= ord(ch) < 127 else "_" for ch in text).replace("=", ":")
    return clean[:limit] or "X"


def _record_samples(n_times: int, sfreq: float) -> int:
    """Samples per data record: a divisor of ``n_times`` whose duration fits the header."""
    per_second = round(sfreq)
    if not math.isclose(per_second, sfreq):
        raise ValueError(f"BDF needs an integer sampling rate, got {sfreq} Hz")
    for seconds in (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125):
        samples = per_second * seconds
        if samples.is_integer() and n_times % int(samples) == 0:
            return int(samples)
    return per_second


def _chunks(
    recording: mne.io.BaseRaw | GeneratedRecording, stop: int
) -> Iterator[tuple[int, np.ndarray]]:
    """(first sample, all channels (n_channels, k)) of ``recording[:, :stop]`` in chunks."""
    if isinstance(recording, mne.io.BaseRaw):
        step = max(1, CHUNK_VALUES // len(recording.ch_names))
        for start in range(0, stop, step):
            yield start, recording.get_data(start=start, stop=min(start + step, stop))
        return
    for start, block in recording.iter_chunks():
        if start >= stop:
            return
        yield start, block[:, : stop - start]


def _bdf_header(
    info: mne.Info, low: np.ndarray, high: np.ndarray, record: int, n_records: int
) -> tuple[bytes, np.ndarray, np.ndarray]:
    """BDF header bytes (edfio's fields) and each signal's (gain, offset) for digitising."""
    sfreq = float(info["sfreq"])
    signals: list[edfio.BdfSignal] = []
    for k, name in enumerate(info["ch_names"]):
        if name == STIM_CHANNEL:
            signals.append(
                edfio.BdfSignal(
                    np.zeros(record),
                    sfreq,
                    label=STIM_CHANNEL,
                    physical_dimension="Boolean",
                    physical_range=BDF_DIGITAL_RANGE,
                    digital_range=BDF_DIGITAL_RANGE,
                )
            )
            continue
        lo, hi = float(low[k]), float(high[k])
        if hi - lo < 1e-6:
            lo, hi = lo - 1.0, hi + 1.0
        signals.append(
            edfio.BdfSignal(
                np.full(record, lo),
                sfreq,
                label=name,
                transducer_type="Active electrode",
                physical_dimension="uV",
                physical_range=(lo, hi),
                digital_range=BDF_DIGITAL_RANGE,
            )
        )
    description = info.get("description") or ""
    synthetic = description.startswith(SYNTHETIC_TAG)
    meas_date = info.get("meas_date")
    startdate = meas_date.date() if meas_date is not None else datetime.date.today()
    starttime = meas_date.time().replace(tzinfo=None, microsecond=0) if meas_date else None
    recording = edfio.Recording(
        startdate=startdate, equipment_code="virtual_subject" if synthetic else "X"
    )
    code = SYNTHETIC_TAG if synthetic else "X"
    room = _EDF_FIELD_CHARS - len(f"{code} X X X ")
    patient = edfio.Patient(
        code=code, additional=[_edf_token(description, room)] if description else ()
    )
    one_record = edfio.Bdf(
        signals,
        patient=patient,
        recording=recording,
        starttime=starttime,
        data_record_duration=record / round(sfreq),
    )
    buffer = io.BytesIO()
    one_record.write(buffer)
    header = bytearray(buffer.getvalue()[: 256 * (len(signals) + 1)])
    header[236:244] = str(n_records).ljust(8).encode("ascii")
    # edfio's physical -> digital rule: round(value / gain - offset).
    parsed = one_record.signals
    gain = np.array(
        [(s.physical_max - s.physical_min) / (s.digital_max - s.digital_min) for s in parsed]
    )
    offset = np.array(
        [s.physical_max / g - s.digital_max for s, g in zip(parsed, gain, strict=True)]
    )
    return bytes(header), gain, offset


def write_bdf(recording: mne.io.BaseRaw | GeneratedRecording, path: str | Path) -> Path:
    """Write a recording as a 24-bit BDF file with an exact ``Status`` trigger channel.

    Parameters
    ----------
    recording : mne.io.BaseRaw | GeneratedRecording
        EEG channels in volts plus a stim channel named ``"Status"`` holding integer codes;
        a :class:`GeneratedRecording` (e.g. a virtual subject's) is written block by block
        as it is generated.
    path : str | Path
        Target ``.bdf`` file; written to a temporary file first and renamed, so a failure
        never leaves a partial file behind.

    Returns
    -------
    path : Path
        The written file.

    Notes
    -----
    EEG signals are stored in microvolts with each channel's own physical range (24-bit
    resolution: range / 2**24). A trailing part shorter than one data record (<= 1 s, only
    when the length is not a multiple of any record size tried) is cropped. Synthetic data
    keep their ``SYNTHETIC`` description in the patient and recording header fields.
    The data are read twice in chunks (ranges, then samples), so memory stays at a few
    chunks whatever the length; the bytes equal edfio's writer's.
    """
    path = Path(path)
    if path.suffix.lower() != ".bdf":
        raise ValueError(f"BDF files must end in .bdf, got {path.name!r}")
    info = recording.info
    ch_names = list(info["ch_names"])
    if STIM_CHANNEL not in ch_names:
        raise ValueError(f"recording has no {STIM_CHANNEL!r} trigger channel")
    stim = ch_names.index(STIM_CHANNEL)
    eeg = np.array([k != stim for k in range(len(ch_names))])
    sfreq = float(info["sfreq"])
    n_times = recording.n_times
    record = _record_samples(n_times, sfreq)
    n_keep = n_times - n_times % record
    if n_keep == 0:
        raise ValueError(f"recording is shorter than one BDF data record ({record} samples)")

    low = np.full(len(ch_names), np.inf)
    high = np.full(len(ch_names), -np.inf)
    finite = np.ones(len(ch_names), dtype=bool)
    for _, block in _chunks(recording, n_keep):
        finite &= np.isfinite(block).all(axis=1)
        # min/max commute with the (monotonic) scaling to microvolts below.
        low = np.minimum(low, block.min(axis=1))
        high = np.maximum(high, block.max(axis=1))
    bad = [
        name for name, ok, is_eeg in zip(ch_names, finite, eeg, strict=True) if is_eeg and not ok
    ]
    if bad:
        raise ValueError(f"channel {bad[0]!r} contains NaN or infinite samples")
    codes_low, codes_high = np.rint(low[stim]), np.rint(high[stim])
    if codes_low < BDF_DIGITAL_RANGE[0] or codes_high > BDF_DIGITAL_RANGE[1]:
        raise ValueError(f"{STIM_CHANNEL} codes do not fit in 24 bits")
    scale = np.where(eeg, 1e6, 1.0)
    header, gain, offset = _bdf_header(
        info,
        low.astype(np.float64) * scale,
        high.astype(np.float64) * scale,
        record,
        n_keep // record,
    )

    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(header)
            carry = np.empty((len(ch_names), 0))
            for _, block in _chunks(recording, n_keep):
                values = np.concatenate([carry, block], axis=1) if carry.size else block
                n_whole = values.shape[1] - values.shape[1] % record
                _write_records(fh, values[:, :n_whole], eeg, stim, gain, offset, record)
                carry = values[:, n_whole:]
            if carry.shape[1]:
                raise RuntimeError("recording ended inside a data record")
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def _write_records(
    fh,
    values: np.ndarray,
    eeg: np.ndarray,
    stim: int,
    gain: np.ndarray,
    offset: np.ndarray,
    record: int,
) -> None:
    """Append whole data records of ``values`` (channels x samples, volts/codes) to ``fh``."""
    step = max(1, CHUNK_VALUES // 4 // len(values) // record) * record
    for start in range(0, values.shape[1], step):
        physical = values[:, start : start + step].astype(np.float64)
        physical[eeg] *= 1e6
        physical[stim] = np.rint(physical[stim])
        physical /= gain[:, None]
        physical -= offset[:, None]
        digital = np.round(physical).astype("<i4")
        n_records = digital.shape[1] // record
        # A data record holds every signal's samples in turn, 3 bytes little-endian each.
        records = digital.reshape(len(digital), n_records, record).transpose(1, 0, 2)
        as_bytes = np.ascontiguousarray(records).view(np.uint8).reshape(*records.shape, 4)
        fh.write(np.ascontiguousarray(as_bytes[..., :3]).tobytes())
