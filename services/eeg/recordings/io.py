"""Recording files: validated reading of BDF/EDF/FIF/BrainVision/EEGLAB/XDF, events, sha256.

The format of a file is read from its header (:func:`detect_format`), never from its name;
a name that says otherwise is reported (:func:`format_mismatch`). EDF/BDF files whose size
disagrees with their header (truncated uploads and copies) are refused with the reason.
BrainVision and XDF are read by :mod:`services.eeg.recordings.formats`; any cap whose channels carry
standard 10-20/10-10 names (directly or through the rig's channel map) and the ErrP's
fronto-central sites is accepted (:mod:`services.eeg.recordings.channels`), at any rate from 128 Hz.

Recordings are read lazily (``preload=False``) and validated, written and epoched in chunks,
so no step holds a full-length float64 copy of a long recording (a 20-minute 64-channel
2048 Hz recording is 1.3 GB in float64).

BDF files are written by :func:`services.eeg.recordings.bdf.write_bdf` (also importable from here).
"""

from __future__ import annotations

import hashlib
import logging
import re
import struct
import zipfile
from pathlib import Path
from typing import Literal

import mne
import numpy as np
from mne.io.edf.edf import RawBDF, RawEDF

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR
from services.eeg.recordings.bdf import BDF_DIGITAL_RANGE, CHUNK_VALUES, write_bdf
from services.eeg.recordings.channels import ChannelError, resolve_channels
from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_TAG, TRIGGER_MASK
from services.eeg.recordings.formats import (
    EventLabels,
    FormatError,
    apply_event_labels,
    is_brainvision,
    is_eeglab,
    read_brainvision,
    read_eeglab,
    read_xdf,
)
from services.eeg.recordings.status_channel import with_status
from services.eeg.signal.preprocessing import PreprocessingParams

__all__ = [
    "BDF_DIGITAL_RANGE",
    "EventLabels",
    "RecordingError",
    "RecordingFormat",
    "action_events",
    "detect_format",
    "file_sha256",
    "format_mismatch",
    "is_synthetic",
    "read_recording",
    "validate_recording",
    "write_bdf",
]

logger = logging.getLogger(__name__)

RecordingFormat = Literal["bdf", "edf", "fif", "brainvision", "eeglab", "xdf"]
SUPPORTED_SUFFIXES = (
    ".bdf", ".edf", ".fif", ".vhdr", ".set", ".zip", ".xdf", ".brainvision", ".eeglab"
)  # fmt: skip
"""``.zip``: a zipped BrainVision set or EEGLAB dataset; ``.brainvision`` and ``.eeglab``:
those as the EEG service stores them."""
_FORMAT_SUFFIXES = {
    "bdf": (".bdf",),
    "edf": (".edf",),
    "fif": (".fif",),
    "brainvision": (".vhdr", ".zip", ".brainvision"),
    "eeglab": (".set", ".zip", ".eeglab"),
    "xdf": (".xdf",),
}
MIN_SFREQ = 128.0
MAX_SFREQ = 20000.0
MIN_DURATION_S = 5.0
FLAT_STD_V = 1e-9
"""A channel whose standard deviation is below 1 nV is flat (disconnected or saturated)."""
CLIPPED_MAX_LEVELS = 4
"""A channel whose samples take at most this many values over its first 10 s is clipped: a
physical range far narrower than the signal (e.g. an export's range given in volts where the
writer expects microvolts) leaves the digital extremes; real EEG takes thousands of values."""
MAX_STD_V = 1.0
"""A channel whose standard deviation exceeds 1 V is not EEG in volts (no EEG amplifier's
input range reaches it): typically microvolts stored as volts, or a unit the file misstates."""
_XDF_MAGIC = b"XDF:"
_BDF_MAGIC = b"\xffBIOSEMI"
_EDF_MAGIC = b"0       "
_FIF_FILE_ID = (100, 31, 20)
"""kind (FIFF_FILE_ID), type (id struct) and size of the first tag of every FIF file."""
_BYTES_PER_SAMPLE = {"bdf": 3, "edf": 2}
_ABSOLUTE_PATH = re.compile(r"(?<![\w.])(?:/[\w.\-+@~]+)+/([\w.\-+@~]+)")


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


# ----------------------------------------------------------------------------- format


def detect_format(path: str | Path, *, name: str | None = None) -> RecordingFormat:
    """The format of a recording file, from its first bytes (the name is not consulted).

    BDF starts with ``0xFF`` + ``"BIOSEMI"``, EDF with ``"0"`` and seven spaces, FIF
    with the file-id tag (kind 100, type 31, size 20, big-endian), XDF with ``"XDF:"``,
    a BrainVision header with ``"Brain Vision Data Exchange Header File"``, an EEGLAB
    ``.set`` with ``"MATLAB "``; a zip holding a ``.vhdr`` is a BrainVision set, one
    holding a ``.set`` an EEGLAB dataset.

    Parameters
    ----------
    path : str | Path
        The file.
    name : str | None
        Name used in error messages (default: the file's own name).

    Raises
    ------
    RecordingError
        If the header matches none of the formats.
    """
    path = Path(path)
    shown = _display_name(path, name)
    with path.open("rb") as fh:
        head = fh.read(64)
    if head.startswith(_XDF_MAGIC):
        return "xdf"
    if is_brainvision(path, head):
        return "brainvision"
    if is_eeglab(path, head):
        return "eeglab"
    if head.startswith(_BDF_MAGIC):
        return "bdf"
    if head.startswith(_EDF_MAGIC):
        return "edf"
    if len(head) >= 12 and struct.unpack(">iii", head[:12]) == _FIF_FILE_ID:
        return "fif"
    unreadable = f"{shown}: not a readable BDF, EDF, FIF, BrainVision, EEGLAB or XDF file"
    if head.startswith((b"PK\x03\x04", b"PK\x05\x06")):
        if not zipfile.is_zipfile(path):
            raise RecordingError(f"{unreadable}: a damaged or truncated zip (it cannot be opened)")
        raise RecordingError(
            f"{unreadable}: a zip without a BrainVision .vhdr or an EEGLAB .set (a zip is "
            "read only as a BrainVision set, its .vhdr, .vmrk and .eeg, or as an EEGLAB "
            "dataset, its .set and .fdt; upload other formats unzipped)"
        )
    raise RecordingError(f"{unreadable} (its first bytes match none of them)")


def format_mismatch(name: str, fmt: RecordingFormat) -> str | None:
    """A one-line note when ``name``'s suffix names another format than the content's."""
    suffix = Path(name).suffix.lower()
    if suffix in _FORMAT_SUFFIXES[fmt] or suffix not in SUPPORTED_SUFFIXES:
        return None
    shown_fmt = {"brainvision": "BrainVision", "eeglab": "EEGLAB"}.get(fmt, fmt.upper())
    return (
        f"{Path(name).name}: the file's header says {shown_fmt}, not {suffix[1:].upper()}; "
        f"it is read as {shown_fmt}"
    )


def _display_name(path: Path, name: str | None) -> str:
    return Path(name).name if name else path.name


def _scrub_paths(text: str, path: Path, shown: str) -> str:
    """``text`` without directory names: the file's path becomes ``shown``."""
    for form in (repr(path), str(path), repr(str(path)), str(path.resolve())):
        text = text.replace(form, shown)
    return _ABSOLUTE_PATH.sub(r"\1", text)


def _check_edf_layout(path: Path, fmt: Literal["bdf", "edf"], shown: str) -> None:
    """Refuse an EDF/BDF file whose size disagrees with its header (e.g. a truncated copy)."""
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(256)
        if len(head) < 256:
            raise RecordingError(f"{shown}: truncated header ({len(head)} of 256 bytes)")
        try:
            header_bytes = int(head[184:192])
            n_records = int(head[236:244])
            record_s = float(head[244:252])
            n_signals = int(head[252:256])
        except ValueError as exc:
            raise RecordingError(f"{shown}: malformed {fmt.upper()} header ({exc})") from exc
        if n_signals < 1 or header_bytes != 256 * (n_signals + 1):
            raise RecordingError(
                f"{shown}: malformed {fmt.upper()} header ({n_signals} signals in a "
                f"{header_bytes}-byte header)"
            )
        fh.seek(256 + 216 * n_signals)
        field = fh.read(8 * n_signals)
    if len(field) < 8 * n_signals or size < header_bytes:
        raise RecordingError(f"{shown}: truncated header ({size} of {header_bytes} bytes)")
    try:
        per_record = [int(field[8 * i : 8 * i + 8]) for i in range(n_signals)]
    except ValueError as exc:
        raise RecordingError(f"{shown}: malformed {fmt.upper()} header ({exc})") from exc
    record_bytes = sum(per_record) * _BYTES_PER_SAMPLE[fmt]
    data_bytes = size - header_bytes
    if record_bytes <= 0:
        raise RecordingError(f"{shown}: malformed {fmt.upper()} header (empty data records)")
    complete, rest = divmod(data_bytes, record_bytes)
    if n_records == -1:  # allowed while recording: the size decides
        if rest:
            raise RecordingError(
                f"{shown}: truncated: the last data record is incomplete "
                f"({rest} of {record_bytes} bytes)"
            )
        return
    if data_bytes < n_records * record_bytes:
        raise RecordingError(
            f"{shown}: truncated: the header declares {n_records} data records "
            f"({n_records * record_s:g} s) but the file holds {complete} complete records "
            f"({complete * record_s:g} s); {n_records * record_bytes - data_bytes} bytes "
            "are missing (was the copy or upload cut short?)"
        )
    if data_bytes > n_records * record_bytes:
        raise RecordingError(
            f"{shown}: {data_bytes - n_records * record_bytes} bytes follow the "
            f"{n_records} data records its header declares (damaged or concatenated file)"
        )


def _check_fif_layout(path: Path, shown: str) -> None:
    """Refuse a FIF file whose tags run past its end (e.g. a truncated copy).

    Every FIF tag is a 16-byte header (kind, type, size, next; big-endian) and ``size``
    bytes of data; ``next`` is 0 for the tag that follows, a byte position, or -1 (none).
    MNE reads a cut file's header and fails only when it reaches the missing samples.
    """
    size = path.stat().st_size
    pos, seen = 0, set()
    with path.open("rb") as fh:
        while pos < size and pos not in seen:
            seen.add(pos)
            fh.seek(pos)
            head = fh.read(16)
            if len(head) < 16:
                raise RecordingError(
                    f"{shown}: truncated: the FIF file ends inside a tag header at byte {pos} "
                    f"of {size} (was the copy or upload cut short?)"
                )
            _, _, tag_size, next_pos = struct.unpack(">iIii", head)
            end = pos + 16 + tag_size
            if tag_size < 0 or end > size:
                raise RecordingError(
                    f"{shown}: truncated: a FIF tag at byte {pos} holds {tag_size} bytes but "
                    f"the file ends after {size - pos - 16} (was the copy or upload cut short?)"
                )
            if next_pos == 0:
                pos = end
            elif next_pos > 0:
                pos = next_pos
            else:
                break


def _bdf_scaled_status(path: Path, n_times: int) -> np.ndarray | None:
    """The codes of a BDF ``Status`` signal written with a scaled physical range, else None.

    BioSemi (and :func:`write_bdf`) store the trigger word with physical range = digital
    range; MNE reads any BDF ``Status`` signal as that raw word. ``mne.export.export_raw``
    instead maps the codes' physical range (e.g. 0..2) onto the digital range, which MNE
    then reads as nonsense (1 for no event, 0 for code 1...). Here such a signal is decoded
    through its header: physical = pmin + (digital - dmin) * (pmax - pmin) / (dmax - dmin).
    """
    with path.open("rb") as fh:
        head = fh.read(256)
        header_bytes, n_records = int(head[184:192]), int(head[236:244])
        n_signals = int(head[252:256])
        fields = fh.read(header_bytes - 256)

    def column(offset: int, width: int) -> list[bytes]:
        """One per-signal header field (``offset``: bytes before it per signal)."""
        start = offset * n_signals
        ends = range(start, start + width * n_signals, width)
        return [fields[end : end + width].strip() for end in ends]

    labels = [label.decode("ascii", "replace").lower() for label in column(0, 16)]
    if STIM_CHANNEL.lower() not in labels:
        return None
    index = labels.index(STIM_CHANNEL.lower())
    pmin, pmax, dmin, dmax = (float(column(offset, 8)[index]) for offset in (104, 112, 120, 128))
    if (pmin, pmax) == (dmin, dmax) or dmax == dmin:
        return None
    per_record = [int(value) for value in column(216, 8)]
    n_status = per_record[index]
    record_bytes = 3 * sum(per_record)
    if n_records == -1:
        n_records = (path.stat().st_size - header_bytes) // record_bytes
    start = 3 * sum(per_record[:index])
    records = np.memmap(
        path, dtype=np.uint8, mode="r", offset=header_bytes, shape=(n_records, record_bytes)
    )
    raw_bytes = np.asarray(records[:, start : start + 3 * n_status]).reshape(-1, 3)
    digital = raw_bytes.astype(np.int32) @ np.array([1, 1 << 8, 1 << 16], dtype=np.int32)
    digital = np.where(digital >= 1 << 23, digital - (1 << 24), digital)
    physical = pmin + (digital - dmin) * ((pmax - pmin) / (dmax - dmin))
    codes = np.rint(physical)
    if codes.size != n_times:  # fewer Status samples per record than the EEG: hold each
        codes = codes[np.arange(n_times) * codes.size // n_times]
    return codes


# ----------------------------------------------------------------------------- reading


def _edf_header_fields(path: Path, shown: str) -> tuple[str, str]:
    """The patient and recording identification fields of an EDF/BDF header."""
    with path.open("rb") as fh:
        head = fh.read(168)
    if len(head) < 168:
        raise RecordingError(f"{shown}: truncated header ({len(head)} bytes)")
    return (
        head[8:88].decode("ascii", "replace").strip(),
        head[88:168].decode("ascii", "replace").strip(),
    )


def _read_any(
    path: Path,
    fmt: RecordingFormat,
    shown: str,
    preload: bool,
    labels: EventLabels,
    xdf_streams: tuple[str | None, str | None],
) -> mne.io.BaseRaw:
    if fmt in ("brainvision", "eeglab", "xdf"):
        try:
            if fmt == "xdf":
                return read_xdf(
                    path, shown, labels, stream=xdf_streams[0], marker_stream=xdf_streams[1]
                )
            if fmt == "eeglab":
                return apply_event_labels(read_eeglab(path, shown), labels)
            return apply_event_labels(read_brainvision(path, shown, preload=preload), labels)
        except FormatError as exc:
            raise RecordingError(_scrub_paths(str(exc), path, shown)) from exc
    if fmt == "fif":
        _check_fif_layout(path, shown)
    else:
        _check_edf_layout(path, fmt, shown)
    try:
        if fmt == "bdf":  # the classes, not read_raw_*: those insist on the suffix
            raw = RawBDF(path, preload=preload, verbose="error")
        elif fmt == "edf":
            raw = RawEDF(path, preload=preload, verbose="error")
        else:
            raw = mne.io.read_raw_fif(path, preload=preload, verbose="error")
    except Exception as exc:
        reason = _scrub_paths(str(exc), path, shown)
        raise RecordingError(f"{shown}: not a readable {fmt.upper()} file ({reason})") from exc
    if fmt != "fif":
        patient, recording = _edf_header_fields(path, shown)
        fields = patient.split(" ", 4)
        additional = fields[4] if len(fields) == 5 else ""
        if fields[0] == SYNTHETIC_TAG or SYNTHETIC_TAG in recording:
            description = additional.replace("_", " ").replace(":", "=")
            if not description.startswith(SYNTHETIC_TAG):
                description = f"{SYNTHETIC_TAG} (file header: {patient} / {recording})"
            raw.info["description"] = description
    if fmt == "bdf":
        try:
            codes = _bdf_scaled_status(path, raw.n_times)
        except ValueError as exc:
            raise RecordingError(f"{shown}: malformed BDF header ({exc})") from exc
        if codes is not None:
            raw = with_status(raw, codes)
    return apply_event_labels(raw, labels)


def read_recording(
    path: str | Path,
    *,
    name: str | None = None,
    preload: bool = False,
    ch_names: list[str] | None = None,
    channel_map: dict[str, str] | None = None,
    labels: EventLabels | None = None,
    xdf_stream: str | None = None,
    xdf_marker_stream: str | None = None,
    min_sfreq: float = MIN_SFREQ,
    min_duration_s: float = MIN_DURATION_S,
) -> mne.io.BaseRaw:
    """Read and validate an EEG recording (BDF, EDF, FIF, BrainVision, EEGLAB or XDF).

    Parameters
    ----------
    path : str | Path
        The file: ``.bdf``, ``.edf``, ``.fif``, ``.xdf``, a BrainVision ``.vhdr`` (its
        ``.vmrk`` and ``.eeg`` beside it) or a ``.zip`` of those three, an EEGLAB ``.set``
        (its ``.fdt``, if any, beside it) or a ``.zip`` of the two. The format is read
        from the content, and a suffix naming another format is logged as a warning (see
        :func:`format_mismatch`).
    name : str | None
        Name of the file in messages (e.g. the uploaded file's name); default the file's
        own name. Messages never contain directories.
    preload : bool
        Load all samples into memory (float64: 1.3 GB for 20 minutes of 64 channels at
        2048 Hz). By default samples are read from the file when asked for, and
        validation reads the file in chunks; a ``Status`` channel made from annotations or
        markers is one value per sample
        (:class:`~services.eeg.recordings.status_channel.RawWithStatus`).
        XDF files and EEGLAB datasets holding double-precision samples are loaded.
    ch_names : list of str | None
        EEG channels (standard names) that must be present, e.g. a classifier's; by
        default any cap of 8-256 standard-named channels with the ErrP's fronto-central
        sites (:func:`services.eeg.recordings.channels.resolve_channels`). Other channels (e.g. EXG)
        are kept, typed ``misc``.
    channel_map : dict | None
        The rig's ``{device_name: standard_name}``; the recording's channels are renamed.
    labels : EventLabels | None
        Which Status codes / annotation or marker texts are correct and error actions
        (default: codes 1/2, texts ``correct``/``error``). Actions end up in ``Status`` as
        codes 1 and 2 whatever their source.
    xdf_stream, xdf_marker_stream : str | None
        XDF only: names of the EEG and marker streams (default: the only stream of type
        ``EEG`` / ``Markers``).
    min_sfreq : float
        Lowest acceptable sampling rate (Hz).
    min_duration_s : float
        Shortest acceptable recording (s).

    Returns
    -------
    raw : mne.io.BaseRaw
        The recording, channels renamed to standard names, ``Status`` typed stim, the EEG
        channels typed EEG and every other channel ``misc``.

    Raises
    ------
    RecordingError
        Naming the problem: missing file, unknown format, content of no known format, a
        truncated EDF/BDF file, unreadable file, sampling rate, missing or unmapped
        channels, no action events, too short, NaN or flat channels.
    """
    path = Path(path)
    shown = _display_name(path, name)
    if not path.is_file():
        raise RecordingError(f"{shown}: no such file")
    suffix = Path(shown).suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise RecordingError(
            f"{shown}: unsupported format {suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(SUPPORTED_SUFFIXES)}"
        )
    fmt = detect_format(path, name=shown)
    note = format_mismatch(shown, fmt)
    if note:
        logger.warning(note)
    raw = _read_any(
        path, fmt, shown, preload, labels or EventLabels(), (xdf_stream, xdf_marker_stream)
    )
    try:
        validate_recording(
            raw,
            ch_names=ch_names,
            channel_map=channel_map,
            min_sfreq=min_sfreq,
            min_duration_s=min_duration_s,
            name=shown,
        )
    except RecordingError:
        raise
    except (ValueError, OSError, EOFError) as exc:  # samples read lazily from a damaged file
        reason = _scrub_paths(f"{type(exc).__name__}: {exc}", path, shown)
        raise RecordingError(
            f"{shown}: damaged {fmt.upper()} file: its samples cannot be read ({reason})"
        ) from exc
    return raw


def _channel_checks(
    raw: mne.io.BaseRaw, picks: list[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per channel of ``picks``: all samples finite, the standard deviation (chunked), and the
    number of distinct sample values over the first 10 s."""
    finite = np.ones(len(picks), dtype=bool)
    count, mean, m2 = 0, np.zeros(len(picks)), np.zeros(len(picks))
    step = max(1, CHUNK_VALUES // len(picks))
    levels = np.zeros(len(picks), dtype=int)
    for start in range(0, raw.n_times, step):
        block = raw.get_data(picks=picks, start=start, stop=min(start + step, raw.n_times))
        finite &= np.isfinite(block).all(axis=1)
        if start == 0:
            window = block[:, : max(1, round(10.0 * raw.info["sfreq"]))]
            levels = np.array([len(np.unique(row)) for row in window])
        # Chan et al.'s pairwise update: exact for large DC offsets, unlike sum of squares.
        n = block.shape[1]
        block_mean = block.mean(axis=1)
        block_m2 = np.square(block - block_mean[:, None]).sum(axis=1)
        delta = block_mean - mean
        total = count + n
        mean = mean + delta * (n / total)
        m2 = m2 + block_m2 + np.square(delta) * (count * n / total)
        count = total
    return finite, np.sqrt(m2 / max(count, 1)), levels


def validate_recording(
    raw: mne.io.BaseRaw,
    *,
    ch_names: list[str] | None = None,
    channel_map: dict[str, str] | None = None,
    min_sfreq: float = MIN_SFREQ,
    min_duration_s: float = MIN_DURATION_S,
    name: str = "recording",
) -> None:
    """Check a recording in place; raises :class:`RecordingError` naming the problem.

    See :func:`read_recording` for the rules. Channels are renamed in place to their
    standard names (through ``channel_map``) and typed: ``Status`` stim, the EEG channels
    EEG, the others ``misc`` (EDF readers type every channel EEG). Samples are read in
    chunks, so a lazily read recording stays on disk.
    """
    sfreq = float(raw.info["sfreq"])
    if not (min_sfreq <= sfreq <= MAX_SFREQ):
        raise RecordingError(
            f"{name}: sampling rate {sfreq:g} Hz is outside {min_sfreq:g}-{MAX_SFREQ:g} Hz"
        )
    try:
        PreprocessingParams().resampling(sfreq)
    except ValueError as exc:
        raise RecordingError(f"{name}: {exc}") from None
    try:
        channels = resolve_channels(raw.ch_names, channel_map, source=name)
    except ChannelError as exc:
        raise RecordingError(str(exc)) from None
    if channels.renamed:
        raw.rename_channels(channels.renamed, verbose="error")
    required = list(ch_names) if ch_names is not None else channels.eeg
    missing = [ch for ch in required if ch not in channels.eeg]
    if missing:
        shown = ", ".join(missing[:8]) + (" ..." if len(missing) > 8 else "")
        raise RecordingError(
            f"{name}: {len(missing)} of {len(required)} required EEG channels missing "
            f"({shown}); found {len(raw.ch_names)} channels"
        )
    if STIM_CHANNEL not in raw.ch_names:
        raise RecordingError(
            f"{name}: no {STIM_CHANNEL!r} trigger channel, and no annotation or marker "
            "mapped to an action (by default the texts 'correct' and 'error')"
        )
    eeg = set(channels.eeg)
    wanted = {
        ch: "stim" if ch == STIM_CHANNEL else "eeg" if ch in eeg else "misc" for ch in raw.ch_names
    }
    types = dict(zip(raw.ch_names, raw.get_channel_types(), strict=True))
    retype = {
        ch: kind
        for ch, kind in wanted.items()
        if types[ch] != kind and (kind != "misc" or types[ch] == "eeg")
    }
    if retype:
        raw.set_channel_types(retype, verbose="error")
    duration = raw.n_times / sfreq
    if duration < min_duration_s:
        raise RecordingError(
            f"{name}: only {duration:.2f} s long; at least {min_duration_s:g} s needed"
        )
    finite, std, levels = _channel_checks(raw, list(required))
    bad_nan = [ch for ch, ok in zip(required, finite, strict=True) if not ok]
    if bad_nan:
        raise RecordingError(f"{name}: NaN or infinite samples in channels {', '.join(bad_nan)}")
    flat = [ch for ch, sd in zip(required, std, strict=True) if sd < FLAT_STD_V]
    if flat:
        hint = (
            " (every EEG channel: are the samples in volts? a file whose unit says microvolts "
            "but holds volts reads a million times too small)"
            if len(flat) == len(required)
            else ""
        )
        raise RecordingError(f"{name}: flat channels (std < 1 nV): {', '.join(flat)}{hint}")
    clipped = [ch for ch, n in zip(required, levels, strict=True) if n <= CLIPPED_MAX_LEVELS]
    if clipped:
        raise RecordingError(
            f"{name}: clipped channels, at most {CLIPPED_MAX_LEVELS} distinct sample values in "
            f"their first 10 s: {', '.join(clipped[:8])}{' ...' if len(clipped) > 8 else ''} "
            "(a physical range far narrower than the signal: was the file exported with its "
            "range in the wrong unit?)"
        )
    huge = [f"{ch} ({sd:.3g} V)" for ch, sd in zip(required, std, strict=True) if sd > MAX_STD_V]
    if huge:
        raise RecordingError(
            f"{name}: EEG amplitudes beyond any amplifier's range, standard deviation over "
            f"{MAX_STD_V:g} V in {', '.join(huge[:8])}{' ...' if len(huge) > 8 else ''}: the "
            "samples are not in volts (microvolts stored as volts, or a wrong unit in the file)"
        )
    if len(action_events(raw)) == 0:
        raise RecordingError(
            f"{name}: no action events (Status codes {TRIGGER_CORRECT} = correct, "
            f"{TRIGGER_ERROR} = error, or annotations/markers mapped to them by the labels)"
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
