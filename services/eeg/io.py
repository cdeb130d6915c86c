"""Recording files: 24-bit BDF writing, validated reading of BDF/EDF/FIF, events, sha256.

BDF triggers: ``mne.export.export_raw(..., fmt="bdf")`` scales a stim channel by its physical
range, after which ``read_raw_bdf`` reads the Status codes wrong (DESIGN §3). We write the
``Status`` signal with edfio's ``BdfSignal`` and a physical range equal to the digital range
(-8388608..8388607), so the codes round-trip exactly.
"""

from __future__ import annotations

import datetime
import hashlib
import math
import os
import tempfile
from pathlib import Path

import edfio
import mne
import numpy as np

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR
from services.eeg.virtual_subject import STIM_CHANNEL, SYNTHETIC_TAG, eeg_channel_names

BDF_DIGITAL_RANGE = (-8388608, 8388607)
SUPPORTED_SUFFIXES = (".bdf", ".edf", ".fif")
MIN_SFREQ = 256.0
MAX_SFREQ = 20000.0
MIN_DURATION_S = 5.0
FLAT_STD_V = 1e-9
"""A channel whose standard deviation is below 1 nV is flat (disconnected or saturated)."""
TRIGGER_MASK = 0xFF
"""Low byte of ``Status``: BioSemi amplifiers set status flags in the upper bits."""
_EDF_FIELD_CHARS = 80


class RecordingError(ValueError):
    """A recording file that cannot be used; the message names the problem."""


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def is_synthetic(raw: mne.io.BaseRaw) -> bool:
    """True when the recording was made by the virtual subject (description or BDF header)."""
    description = raw.info.get("description") or ""
    return description.startswith(SYNTHETIC_TAG)


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


def write_bdf(raw: mne.io.BaseRaw, path: str | Path) -> Path:
    """Write a recording as a 24-bit BDF file with an exact ``Status`` trigger channel.

    Parameters
    ----------
    raw : mne.io.BaseRaw
        EEG channels in volts plus a stim channel named ``"Status"`` holding integer codes.
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
    """
    path = Path(path)
    if path.suffix.lower() != ".bdf":
        raise ValueError(f"BDF files must end in .bdf, got {path.name!r}")
    if STIM_CHANNEL not in raw.ch_names:
        raise ValueError(f"recording has no {STIM_CHANNEL!r} trigger channel")
    sfreq = float(raw.info["sfreq"])
    data = raw.get_data()
    n_times = data.shape[1]
    record = _record_samples(n_times, sfreq)
    n_keep = n_times - n_times % record
    if n_keep == 0:
        raise ValueError(f"recording is shorter than one BDF data record ({record} samples)")
    data = data[:, :n_keep]

    signals: list[edfio.BdfSignal] = []
    for name, row in zip(raw.ch_names, data, strict=True):
        if name == STIM_CHANNEL:
            codes = np.rint(row)
            if codes.min() < BDF_DIGITAL_RANGE[0] or codes.max() > BDF_DIGITAL_RANGE[1]:
                raise ValueError(f"{STIM_CHANNEL} codes do not fit in 24 bits")
            signals.append(
                edfio.BdfSignal(
                    codes,
                    sfreq,
                    label=STIM_CHANNEL,
                    physical_dimension="Boolean",
                    physical_range=BDF_DIGITAL_RANGE,
                    digital_range=BDF_DIGITAL_RANGE,
                )
            )
            continue
        if not np.all(np.isfinite(row)):
            raise ValueError(f"channel {name!r} contains NaN or infinite samples")
        microvolts = row * 1e6
        low, high = float(microvolts.min()), float(microvolts.max())
        if high - low < 1e-6:
            low, high = low - 1.0, high + 1.0
        signals.append(
            edfio.BdfSignal(
                microvolts,
                sfreq,
                label=name,
                transducer_type="Active electrode",
                physical_dimension="uV",
                physical_range=(low, high),
                digital_range=BDF_DIGITAL_RANGE,
            )
        )

    description = raw.info.get("description") or ""
    synthetic = description.startswith(SYNTHETIC_TAG)
    meas_date = raw.info.get("meas_date")
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
    bdf = edfio.Bdf(
        signals,
        patient=patient,
        recording=recording,
        starttime=starttime,
        data_record_duration=record / round(sfreq),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    try:
        bdf.write(tmp_name)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def _edf_header_fields(path: Path) -> tuple[str, str]:
    """The patient and recording identification fields of an EDF/BDF header."""
    with path.open("rb") as fh:
        head = fh.read(168)
    if len(head) < 168:
        raise RecordingError(f"{path.name}: truncated header ({len(head)} bytes)")
    return (
        head[8:88].decode("ascii", "replace").strip(),
        head[88:168].decode("ascii", "replace").strip(),
    )


def _read_any(path: Path) -> mne.io.BaseRaw:
    suffix = path.suffix.lower()
    try:
        if suffix == ".bdf":
            raw = mne.io.read_raw_bdf(path, preload=True, verbose="error")
        elif suffix == ".edf":
            raw = mne.io.read_raw_edf(path, preload=True, verbose="error")
        else:
            raw = mne.io.read_raw_fif(path, preload=True, verbose="error")
    except Exception as exc:
        raise RecordingError(
            f"{path.name}: not a readable {suffix[1:].upper()} file ({exc})"
        ) from exc
    if suffix in (".bdf", ".edf"):
        patient, recording = _edf_header_fields(path)
        fields = patient.split(" ", 4)
        additional = fields[4] if len(fields) == 5 else ""
        if fields[0] == SYNTHETIC_TAG or SYNTHETIC_TAG in recording:
            description = additional.replace("_", " ").replace(":", "=")
            if not description.startswith(SYNTHETIC_TAG):
                description = f"{SYNTHETIC_TAG} (file header: {patient} / {recording})"
            raw.info["description"] = description
    return raw


def read_recording(
    path: str | Path,
    *,
    ch_names: list[str] | None = None,
    min_sfreq: float = MIN_SFREQ,
    min_duration_s: float = MIN_DURATION_S,
) -> mne.io.BaseRaw:
    """Read and validate an EEG recording (BDF, EDF or FIF), fully loaded.

    Parameters
    ----------
    path : str | Path
        The file; the suffix selects the reader.
    ch_names : list of str | None
        EEG channels that must be present (default: the 64 BioSemi names). Other channels
        (e.g. EXG) may be present too; they are kept.
    min_sfreq : float
        Lowest acceptable sampling rate (Hz).
    min_duration_s : float
        Shortest acceptable recording (s).

    Returns
    -------
    raw : mne.io.BaseRaw
        The recording, with ``Status`` typed as stim and the required channels typed EEG.

    Raises
    ------
    RecordingError
        Naming the problem: missing file, unknown format, unreadable file, sampling rate,
        missing channels, missing or empty trigger channel, too short, NaN or flat channels.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise RecordingError(
            f"{path.name}: unsupported format {suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    raw = _read_any(path)
    validate_recording(
        raw, ch_names=ch_names, min_sfreq=min_sfreq, min_duration_s=min_duration_s, name=path.name
    )
    return raw


def validate_recording(
    raw: mne.io.BaseRaw,
    *,
    ch_names: list[str] | None = None,
    min_sfreq: float = MIN_SFREQ,
    min_duration_s: float = MIN_DURATION_S,
    name: str = "recording",
) -> None:
    """Check a loaded recording in place; raises :class:`RecordingError` naming the problem.

    See :func:`read_recording` for the rules. Channel types are fixed in place: ``Status``
    becomes stim and the required channels EEG (EDF readers type every channel EEG).
    """
    sfreq = float(raw.info["sfreq"])
    if not (min_sfreq <= sfreq <= MAX_SFREQ):
        raise RecordingError(
            f"{name}: sampling rate {sfreq:g} Hz is outside {min_sfreq:g}-{MAX_SFREQ:g} Hz"
        )
    required = ch_names if ch_names is not None else eeg_channel_names()
    missing = [ch for ch in required if ch not in raw.ch_names]
    if missing:
        shown = ", ".join(missing[:8]) + (" ..." if len(missing) > 8 else "")
        raise RecordingError(
            f"{name}: {len(missing)} of {len(required)} required EEG channels missing "
            f"({shown}); found {len(raw.ch_names)} channels"
        )
    if STIM_CHANNEL not in raw.ch_names:
        raise RecordingError(f"{name}: no {STIM_CHANNEL!r} trigger channel")
    types = dict(zip(raw.ch_names, raw.get_channel_types(), strict=True))
    retype = {ch: "eeg" for ch in required if types[ch] != "eeg"}
    if types[STIM_CHANNEL] != "stim":
        retype[STIM_CHANNEL] = "stim"
    if retype:
        raw.set_channel_types(retype, verbose="error")
    duration = raw.n_times / sfreq
    if duration < min_duration_s:
        raise RecordingError(
            f"{name}: only {duration:.2f} s long; at least {min_duration_s:g} s needed"
        )
    data = raw.get_data(picks=required)
    bad_nan = [ch for ch, row in zip(required, data, strict=True) if not np.all(np.isfinite(row))]
    if bad_nan:
        raise RecordingError(f"{name}: NaN or infinite samples in channels {', '.join(bad_nan)}")
    flat = [ch for ch, sd in zip(required, data.std(axis=1), strict=True) if sd < FLAT_STD_V]
    if flat:
        raise RecordingError(f"{name}: flat channels (std < 1 nV): {', '.join(flat)}")
    if len(action_events(raw)) == 0:
        raise RecordingError(
            f"{name}: {STIM_CHANNEL} holds no action trigger "
            f"(codes {TRIGGER_CORRECT} = correct, {TRIGGER_ERROR} = error)"
        )


def action_events(raw: mne.io.BaseRaw) -> np.ndarray:
    """Action onsets from the ``Status`` channel as an MNE events array.

    Returns
    -------
    events : ndarray of int, shape (n_actions, 3)
        Sample index (including ``raw.first_samp``), previous value, and code 1 (correct)
        or 2 (error). Other codes (low byte of ``Status``) are ignored.
    """
    if STIM_CHANNEL not in raw.ch_names:
        raise RecordingError(f"no {STIM_CHANNEL!r} trigger channel")
    events = mne.find_events(
        raw,
        stim_channel=STIM_CHANNEL,
        shortest_event=1,
        consecutive=True,
        mask=TRIGGER_MASK,
        mask_type="and",
        initial_event=True,
        verbose="error",
    )
    keep = np.isin(events[:, 2], (TRIGGER_CORRECT, TRIGGER_ERROR))
    return events[keep]
