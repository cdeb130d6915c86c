"""Recording formats beside BDF/EDF/FIF: BrainVision, EEGLAB and XDF; action labels from events.

* **BrainVision** (BrainAmp, actiCHamp...): a ``.vhdr`` header with its ``.vmrk`` markers and
  ``.eeg`` samples. Read from the ``.vhdr`` path (the two others beside it) or from a zip
  holding the three (how the EEG service takes an upload: one file).
* **EEGLAB**: a ``.set`` dataset (a MATLAB file) holding its samples or naming the ``.fdt``
  beside it that does; read from the ``.set`` path or from a zip holding the two. Its events
  (``EEG.event``, their ``type``) are read as annotations.
* **XDF** (LabRecorder): the EEG stream is chosen by name (or the only stream of type
  ``EEG``), its channel labels and units from the stream description; actions come from a
  marker stream (by name, or the only ``Markers`` stream) or from a ``Status`` channel.

Whatever the source of the events (``Status`` codes, EDF+/BrainVision/EEGLAB annotations, XDF
markers), :class:`EventLabels` says which ones are correct and error actions, and they
become the ``Status`` codes 1 (correct) and 2 (error) every later step reads.
"""

from __future__ import annotations

import configparser
import json
import re
import shutil
import tempfile
import weakref
import zipfile
import zlib
from contextlib import suppress
from pathlib import Path
from typing import Literal

import mne
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR
from services.core.markers import ActionMarker
from services.eeg.recordings.conventions import STIM_CHANNEL, SYNTHETIC_ELEMENT, SYNTHETIC_TAG
from services.eeg.recordings.status_channel import with_status

__all__ = [
    "BRAINVISION_MAGIC",
    "EventLabels",
    "FormatError",
    "apply_event_labels",
    "is_eeglab",
    "read_brainvision",
    "read_eeglab",
    "read_xdf",
]

Label = Literal["correct", "error"]
BRAINVISION_MAGIC = (b"Brain Vision Data Exchange Header File", b"BrainVision Data Exchange")
EEGLAB_MAGIC = b"MATLAB "
"""The text every MATLAB file (``MATLAB 5.0 MAT-file``, ``MATLAB 7.3 MAT-file``) begins with."""
MAX_UNZIPPED_BYTES = 4 << 30
"""Largest BrainVision set or EEGLAB dataset read out of a zip (4 GiB: 20 minutes of 256
channels at 1 kHz)."""
MAX_HEADER_BYTES = 1 << 20
"""Largest ``.vhdr`` read (a header is a few kB of text)."""
MAX_COMPRESSION_RATIO = 100
"""Largest unzipped/zipped size of a zip member past ``RATIO_FREE_BYTES`` (EEG samples
compress 1.1-4 times; a zip bomb of zeros, about 1000 times: 2 MB that unzip to 2 GiB)."""
RATIO_FREE_BYTES = 16 << 20
"""Members up to this size unzipped are not held to ``MAX_COMPRESSION_RATIO`` (headers and
marker files are small and compress well)."""
MAX_RATE_MISMATCH = 0.01
"""Largest relative difference between an XDF EEG stream's nominal rate and the rate its
timestamps give (clock drift is ppm; a percent is a wrong rate or lost samples)."""
UNZIPPED_KEY = "bgrl_unzipped"
"""Key of a recording's reader data holding the :class:`UnzippedFolder` it reads from."""
_TRIGGER = {"correct": TRIGGER_CORRECT, "error": TRIGGER_ERROR}
_BINARY_FORMAT_BYTES = {"INT_16": 2, "UINT_16": 2, "INT_32": 4, "IEEE_FLOAT_32": 4}
_MARKER_POSITION = re.compile(r"^Mk\d+=[^,\r\n]*,[^,\r\n]*,\s*(\d+)", re.MULTILINE)
"""The (1-based) sample position of each ``Mk<n>=<type>,<description>,<position>,...``."""
_SAMPLES_FILE = re.compile(r"([^/\\\s]+\.fdt)", re.IGNORECASE)
"""The name of the ``.fdt`` file in MNE's "File ... not found" message."""
_CODE_DESCRIPTION = re.compile(r"^(?:S|R)?\s*(\d+)$")
"""``"S  1"`` (a BrainVision stimulus marker), ``"R  2"`` (response) or a bare ``"1"``."""
_VOLT_SCALE = {
    "v": 1.0,
    "volt": 1.0,
    "volts": 1.0,
    "mv": 1e-3,
    "millivolt": 1e-3,
    "millivolts": 1e-3,
    "uv": 1e-6,
    "µv": 1e-6,
    "μv": 1e-6,
    "microvolt": 1e-6,
    "microvolts": 1e-6,
    "nv": 1e-9,
    "nanovolts": 1e-9,
}


class FormatError(ValueError):
    """A BrainVision/EEGLAB/XDF file or its events cannot be used; the message says why."""


class EventLabels(BaseModel):
    """Which events are correct and which error actions (others are ignored).

    Attributes
    ----------
    codes : dict
        Trigger code -> label, for the ``Status`` channel, BrainVision stimulus markers
        (``S  1``) and numeric annotations. Default: 1 correct, 2 error.
    descriptions : dict
        Annotation / XDF marker text -> label, compared case-insensitively, on the whole
        description and on the part after its last ``/`` (BrainVision's ``Comment/error``).
        Default: ``correct`` and ``error``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    codes: dict[int, Label] = Field(
        default_factory=lambda: {TRIGGER_CORRECT: "correct", TRIGGER_ERROR: "error"}
    )
    descriptions: dict[str, Label] = Field(
        default_factory=lambda: {"correct": "correct", "error": "error"}
    )

    @property
    def is_default_codes(self) -> bool:
        return self.codes == {TRIGGER_CORRECT: "correct", TRIGGER_ERROR: "error"}

    def trigger_for(self, description: str) -> int | None:
        """Status code (1/2) of an annotation or marker text, or None when not an action."""
        text = description.strip()
        lowered = {key.strip().lower(): value for key, value in self.descriptions.items()}
        for candidate in (text, text.rsplit("/", 1)[-1].strip()):
            if candidate.lower() in lowered:
                return _TRIGGER[lowered[candidate.lower()]]
            match = _CODE_DESCRIPTION.match(candidate)
            if match and int(match.group(1)) in self.codes:
                return _TRIGGER[self.codes[int(match.group(1))]]
        return None

    def summary(self) -> str:
        """The mapping in one line, for messages."""
        codes = ", ".join(f"{code} = {label}" for code, label in sorted(self.codes.items()))
        texts = ", ".join(f"{text!r} = {label}" for text, label in self.descriptions.items())
        return f"codes {codes}; descriptions {texts}"


def apply_event_labels(raw: mne.io.BaseRaw, labels: EventLabels) -> mne.io.BaseRaw:
    """Make ``Status`` hold the actions as codes 1 (correct) / 2 (error).

    A ``Status`` channel is used when present (its codes mapped by ``labels.codes``; with
    the default mapping it is left as it is, not even loaded). Without one, the
    annotations (EDF+, BrainVision, FIF) become a ``Status`` channel with a one-sample
    pulse per action annotation; with no action annotation either, ``raw`` is returned
    as it is (and refused for lacking a ``Status`` channel).
    """
    if STIM_CHANNEL in raw.ch_names:
        if labels.is_default_codes:
            return raw
        old = raw.get_data(picks=[STIM_CHANNEL])[0].astype(np.int64) & 0xFF
        new = np.zeros_like(old)
        for code, label in labels.codes.items():
            new[old == code] = _TRIGGER[label]
        return with_status(raw, new.astype(np.float64))
    status = np.zeros(raw.n_times)
    sfreq = raw.info["sfreq"]
    for annotation in raw.annotations:
        trigger = labels.trigger_for(str(annotation["description"]))
        if trigger is None:
            continue
        sample = round((annotation["onset"] - raw.first_time) * sfreq)
        if 0 <= sample < raw.n_times:
            status[sample] = trigger
    return with_status(raw, status) if status.any() else raw


# ----------------------------------------------------------------------------- BrainVision


def _referenced_files(vhdr_text: str, shown: str) -> tuple[str, str]:
    """The ``DataFile`` and ``MarkerFile`` a BrainVision header names."""
    body = vhdr_text.split("\n", 1)[1] if "\n" in vhdr_text else ""
    parser = configparser.ConfigParser(interpolation=None, strict=False)
    try:
        parser.read_string(body)
        common = parser["Common Infos"]
        named = {key: Path(common[key].strip()).name for key in ("DataFile", "MarkerFile")}
    except (configparser.Error, KeyError) as exc:
        raise FormatError(
            f"{shown}: malformed BrainVision header (no DataFile/MarkerFile in "
            f"[Common Infos]: {exc})"
        ) from exc
    for key, name in named.items():
        if name in ("", ".", "..") or name.lower().endswith(".vhdr"):
            raise FormatError(
                f"{shown}: malformed BrainVision header ({key}={common[key].strip()!r} names "
                "no data or marker file)"
            )
    return named["DataFile"], named["MarkerFile"]


def _read_vhdr(vhdr: Path, shown: str, preload: bool) -> mne.io.BaseRaw:
    text = vhdr.read_text(encoding="utf-8", errors="replace")
    data_file, marker_file = _referenced_files(text, shown)
    absent = [name for name in (data_file, marker_file) if not (vhdr.parent / name).is_file()]
    if absent:
        raise FormatError(
            f"{shown}: the header refers to {' and '.join(absent)}, not found beside it "
            "(keep the .vhdr, .vmrk and .eeg together; upload them as one zip)"
        )
    try:
        raw = mne.io.read_raw_brainvision(vhdr, preload=preload, verbose="error")
    except Exception as exc:
        raise FormatError(f"{shown}: not a readable BrainVision set ({exc})") from exc
    _check_brainvision_length(text, vhdr.parent / data_file, vhdr.parent / marker_file, raw, shown)
    return raw


def _binary_layout(vhdr_text: str) -> tuple[int, int, int | None] | None:
    """Bytes per sample of all channels, the number of channels and the declared
    ``DataPoints`` (if any) of a binary BrainVision set; None when the header does not say."""
    parser = configparser.ConfigParser(interpolation=None, strict=False)
    with suppress(configparser.Error):
        parser.read_string(vhdr_text.split("\n", 1)[1] if "\n" in vhdr_text else "")
    common = parser["Common Infos"] if parser.has_section("Common Infos") else {}
    binary = parser["Binary Infos"] if parser.has_section("Binary Infos") else {}
    sample_bytes = _BINARY_FORMAT_BYTES.get(str(binary.get("BinaryFormat", "")).strip().upper())
    n_channels = str(common.get("NumberOfChannels", "")).strip()
    points = str(common.get("DataPoints", "")).strip()
    if (
        str(common.get("DataFormat", "BINARY")).strip().upper() != "BINARY"
        or not sample_bytes
        or not n_channels.isdigit()
        or int(n_channels) == 0
    ):
        return None
    declared = int(points) if points.isdigit() else None
    return sample_bytes * int(n_channels), int(n_channels), declared


def _check_brainvision_length(
    vhdr_text: str, data_path: Path, marker_path: Path, raw: mne.io.BaseRaw, shown: str
) -> None:
    """Refuse a truncated BrainVision set: a binary ``.eeg`` that ends inside a sample, or
    markers after the last sample (MNE reads the part that is there, silently)."""
    refusal = _samples_size_refusal(vhdr_text, data_path.stat().st_size, shown)
    if refusal:
        raise FormatError(refusal)
    markers = marker_path.read_text(encoding="utf-8", errors="replace")
    positions = [int(match) for match in _MARKER_POSITION.findall(markers)]
    if positions and max(positions) > raw.n_times:
        raise FormatError(
            f"{shown}: truncated: the .vmrk places markers up to sample {max(positions)} "
            f"but the .eeg holds {raw.n_times} samples (was the copy cut short?)"
        )


def _check_members(members: list[zipfile.ZipInfo], shown: str) -> None:
    """Refuse, before anything is unzipped, members that would unzip to more than
    ``MAX_UNZIPPED_BYTES`` together or that claim more than ``MAX_COMPRESSION_RATIO`` times
    their zipped size (a zip bomb, or a header lying about a member's size)."""
    size = sum(info.file_size for info in members)
    if size > MAX_UNZIPPED_BYTES:
        raise FormatError(f"{shown}: {size} bytes unzipped; at most {MAX_UNZIPPED_BYTES} are read")
    for info in members:
        ratio = info.file_size / max(info.compress_size, 1)
        if info.file_size > RATIO_FREE_BYTES and ratio > MAX_COMPRESSION_RATIO:
            raise FormatError(
                f"{shown}: {Path(info.filename).name} would unzip to {info.file_size} bytes, "
                f"{ratio:.0f} times its {info.compress_size} zipped bytes (EEG samples compress "
                f"at most a few times; more than {MAX_COMPRESSION_RATIO} is refused as a zip "
                "bomb or a damaged zip)"
            )


class UnzippedFolder:
    """A temporary folder holding the files unzipped from an upload, removed once no
    recording reads from it (its recordings hold it; their copies share it)."""

    def __init__(self, prefix: str) -> None:
        self.path = Path(tempfile.mkdtemp(prefix=prefix))
        self._remove = weakref.finalize(self, shutil.rmtree, self.path, ignore_errors=True)

    def __deepcopy__(self, memo: dict) -> UnzippedFolder:
        return self  # a copied recording reads the same files

    def remove(self) -> None:
        """Remove the folder now (recordings reading from it can no longer read)."""
        self._remove()

    @staticmethod
    def attach(raw: mne.io.BaseRaw, folder: UnzippedFolder) -> mne.io.BaseRaw:
        """Keep ``folder`` as long as ``raw`` (or a copy of it) exists."""
        for extras in raw._raw_extras:
            extras[UNZIPPED_KEY] = folder
        return raw


def _unzip(archive: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, shown: str) -> None:
    """Copy one member to ``target``, never more bytes than its header declares (zipfile
    stops there, and a member whose data does not match its header fails its CRC)."""
    try:
        with archive.open(info) as src, target.open("wb") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    except (zipfile.BadZipFile, zlib.error, EOFError) as exc:
        raise FormatError(f"{shown}: a damaged zip ({Path(info.filename).name}: {exc})") from exc


def _samples_size_refusal(vhdr_text: str, size: int, shown: str) -> str | None:
    """Why a ``.eeg`` of ``size`` bytes does not fit its header's recording (a whole number
    of samples of its channels, and the header's ``DataPoints`` if given), or None."""
    layout = _binary_layout(vhdr_text)
    if layout is None:
        return None
    frame, n_channels, data_points = layout
    if size % frame:
        return (
            f"{shown}: truncated: the .eeg file ends inside a sample ({size % frame} bytes of a "
            f"{frame}-byte sample of {n_channels} channels; was the copy cut short?)"
        )
    if data_points is not None and size != data_points * frame:
        return (
            f"{shown}: the .eeg file holds {size // frame} samples; the header declares "
            f"DataPoints={data_points}"
        )
    return None


def read_brainvision(path: Path, shown: str, *, preload: bool = False) -> mne.io.BaseRaw:
    """Read a BrainVision set from its ``.vhdr`` or from a zip holding the three files.

    A zip must hold exactly one ``.vhdr``; only it and the two files it names are taken
    out, into an :class:`UnzippedFolder` the recording reads its samples from (lazily unless
    ``preload``) and that is removed once the recording is gone.
    """
    if not zipfile.is_zipfile(path):
        return _read_vhdr(path, shown, preload)
    with zipfile.ZipFile(path) as archive:
        files = [info for info in archive.infolist() if not info.is_dir()]
        headers = [info for info in files if info.filename.lower().endswith(".vhdr")]
        if len(headers) != 1:
            raise FormatError(
                f"{shown}: a BrainVision zip holds one .vhdr with its .vmrk and .eeg; "
                f"found {len(headers)} .vhdr files"
            )
        _check_members(headers, shown)
        if headers[0].file_size > MAX_HEADER_BYTES:
            raise FormatError(
                f"{shown}: a {headers[0].file_size}-byte .vhdr is no BrainVision header"
            )
        try:
            text = archive.read(headers[0]).decode("utf-8", "replace")
        except (zipfile.BadZipFile, zlib.error, EOFError) as exc:
            raise FormatError(f"{shown}: a damaged zip ({exc})") from exc
        data_file, marker_file = _referenced_files(text, shown)
        # Members are matched by base name (the set may sit in a folder of the zip), and
        # case-insensitively when no exact match exists (sets written on Windows).
        chosen = []
        for name in (data_file, marker_file):
            exact = [info for info in files if Path(info.filename).name == name]
            found = exact or [
                info for info in files if Path(info.filename).name.lower() == name.lower()
            ]
            if not found:
                raise FormatError(f"{shown}: the zip lacks {name} (named by the .vhdr)")
            if len(found) > 1:
                raise FormatError(
                    f"{shown}: the zip holds {len(found)} files named {name} "
                    f"({', '.join(info.filename for info in found[:4])}); keep one set per zip"
                )
            chosen.append(found[0])
        _check_members(chosen, shown)
        # the .eeg's declared size must fit the header, checked before it is unzipped
        if refusal := _samples_size_refusal(text, chosen[0].file_size, shown):
            raise FormatError(refusal)
        header_name = f"{Path(headers[0].filename).stem or 'recording'}.vhdr"
        targets = [header_name, data_file, marker_file]  # MNE wants a lower-case .vhdr
        folder = UnzippedFolder("bgrl-vhdr-")
        try:
            for info, target in zip([headers[0], *chosen], targets, strict=True):
                _unzip(archive, info, folder.path / target, shown)
            raw = _read_vhdr(folder.path / header_name, shown, preload=preload)
        except BaseException:
            folder.remove()
            raise
        return UnzippedFolder.attach(raw, folder)


def _zip_holds(path: Path, head: bytes, suffix: str) -> bool:
    """Whether ``path`` (starting with ``head``) is a zip with a member ending in ``suffix``."""
    if not head.startswith(b"PK\x03\x04"):
        return False
    try:
        with zipfile.ZipFile(path) as archive:
            return any(name.lower().endswith(suffix) for name in archive.namelist())
    except zipfile.BadZipFile:
        return False


def is_brainvision(path: Path, head: bytes) -> bool:
    """A BrainVision header, or a zip holding a ``.vhdr``."""
    return head.startswith(BRAINVISION_MAGIC) or _zip_holds(path, head, ".vhdr")


# ----------------------------------------------------------------------------- EEGLAB


def _embedded_samples_class(set_path: Path) -> str | None:
    """The MATLAB class (``single``, ``double``...) of the samples a ``.set`` holds itself,
    or None when it names a ``.fdt`` (or cannot be listed)."""
    import scipy.io

    try:
        listed = scipy.io.whosmat(set_path)
    except Exception:  # not a MATLAB 5 file: MNE says why below
        return None
    return next((kind for name, _, kind in listed if name == "data" and kind != "char"), None)


class _SamplesInFile:
    """Samples (channels x samples, column-major) at ``offset`` in a file, read a slice of
    samples at a time as ``samples[:, start:stop]`` (how MNE slices embedded samples)."""

    def __init__(self, path: Path, offset: int, shape: tuple[int, int], dtype: str) -> None:
        self.path, self.offset, self.shape, self.dtype = path, offset, shape, np.dtype(dtype)
        self.ndim = 2

    def __getitem__(self, key: tuple[slice, slice]) -> np.ndarray:
        rows, columns = key
        start, stop, step = columns.indices(self.shape[1])
        if rows != slice(None) or step != 1:
            raise IndexError("only samples[:, start:stop] is read")
        n_channels = self.shape[0]
        with self.path.open("rb") as fh:
            fh.seek(self.offset + start * n_channels * self.dtype.itemsize)
            values = np.fromfile(fh, self.dtype, count=max(0, stop - start) * n_channels)
        return values.reshape(-1, n_channels).T

    def __deepcopy__(self, memo: dict) -> _SamplesInFile:
        return self  # nothing in memory to copy


def _samples_in_set(set_path: Path) -> _SamplesInFile | None:
    """The single-precision samples a ``.set`` holds as its uncompressed top-level ``data``
    variable (as eeglabio, hence ``mne.export``, writes them), to be read a slice at a
    time; None for any other layout (MNE then reads them whole)."""
    from scipy.io.matlab._mio5 import MatFile5Reader
    from scipy.io.matlab._mio5_params import miSINGLE

    with set_path.open("rb") as fh:
        reader = MatFile5Reader(fh)
        reader.initialize_read()
        reader.read_file_header()
        while not reader.end_of_stream():
            header, next_position = reader.read_var_header()
            if header.name == b"data":
                if len(header.dims) != 2:
                    return None
                order = reader.byte_order
                mdtype, n_bytes = np.frombuffer(fh.read(8), dtype=f"{order}u4")
                shape = tuple(int(n) for n in header.dims)
                if mdtype != miSINGLE or n_bytes != 4 * shape[0] * shape[1]:
                    return None  # compressed (then a tag of its own), double, ...
                return _SamplesInFile(set_path, fh.tell(), shape, f"{order}f4")
            fh.seek(next_position)
    return None


def _open_set(set_path: Path, shown: str, preload: bool) -> mne.io.BaseRaw:
    """MNE's reading of a ``.set``, its errors as :class:`FormatError`."""
    try:
        return mne.io.read_raw_eeglab(set_path, preload=preload, verbose="error")
    except FileNotFoundError as exc:
        named = _SAMPLES_FILE.search(str(exc))
        raise FormatError(
            f"{shown}: the dataset keeps its samples in "
            f"{named.group(1) if named else 'a .fdt file'}, not found beside it "
            "(keep the .set and .fdt together; upload them as one zip)"
        ) from exc
    except Exception as exc:
        reason = str(exc)
        if "number of trials" in reason.lower():
            reason = "an epoched dataset; export the continuous recording"
        raise FormatError(f"{shown}: not a readable EEGLAB dataset ({reason})") from exc


def _read_set(set_path: Path, shown: str) -> mne.io.BaseRaw:
    """A ``.set`` (its ``.fdt``, if it names one, beside it), read lazily.

    MNE reads the samples a ``.set`` holds itself lazily only from a file named ``.set``
    (the EEG service stores uploads as ``.eeglab``: read through a link of that name), and
    only in single precision: those are read a slice at a time (:func:`_samples_in_set`);
    ``double`` samples are loaded (read lazily, MNE would cast them to float32)."""
    embedded = _embedded_samples_class(set_path)
    folder = None
    if embedded is not None and set_path.suffix.lower() != ".set":
        folder = UnzippedFolder("bgrl-set-")
        (folder.path / "recording.set").symlink_to(set_path.resolve())
    try:
        raw = _open_set(
            folder.path / "recording.set" if folder else set_path,
            shown,
            preload=embedded not in (None, "single"),
        )
        if embedded == "single" and not raw.preload:
            # MNE reads embedded samples whole at the first access, then slices them: give
            # it them as slices read from the file, so only the slices asked for are read
            samples_in_set = _samples_in_set(Path(raw.filenames[0]))
            if samples_in_set is not None and samples_in_set.shape == (
                raw.info["nchan"],
                raw.n_times,
            ):
                raw._raw_extras[0]["cached_data"] = samples_in_set
        samples = Path(raw.filenames[0]) if raw.filenames[0] else None
        expected = 4 * raw.info["nchan"] * raw.n_times  # float32, channels x samples
        if (
            embedded is None
            and samples is not None
            and samples.suffix.lower() == ".fdt"
            and samples.stat().st_size < expected
        ):
            raise FormatError(
                f"{shown}: truncated: the .fdt holds fewer samples than the .set says "
                f"({samples.stat().st_size} of {expected} bytes; was the copy cut short?)"
            )
    except BaseException:
        if folder is not None:
            folder.remove()
        raise
    return raw if folder is None else UnzippedFolder.attach(raw, folder)


def read_eeglab(path: Path, shown: str) -> mne.io.BaseRaw:
    """Read an EEGLAB dataset from its ``.set`` or from a zip holding the ``.set`` and its
    ``.fdt`` (one of each at the most: only they are taken out, into an
    :class:`UnzippedFolder` removed once the recording is gone). Samples are read lazily:
    from the ``.fdt`` a chunk at a time; samples inside the ``.set`` (MATLAB) are read whole
    at the first access."""
    if not zipfile.is_zipfile(path):
        return _read_set(path, shown)
    with zipfile.ZipFile(path) as archive:
        files = [info for info in archive.infolist() if not info.is_dir()]
        sets = [info for info in files if info.filename.lower().endswith(".set")]
        samples = [info for info in files if info.filename.lower().endswith(".fdt")]
        if len(sets) != 1 or len(samples) > 1:
            raise FormatError(
                f"{shown}: an EEGLAB zip holds one .set and at most one .fdt; found "
                f"{len(sets)} .set and {len(samples)} .fdt files"
            )
        chosen = [*sets, *samples]
        _check_members(chosen, shown)
        names = [Path(info.filename).name for info in chosen]
        folder = UnzippedFolder("bgrl-set-")
        try:
            for info, name in zip(chosen, names, strict=True):
                _unzip(archive, info, folder.path / name, shown)
            raw = _read_set(folder.path / names[0], shown)
        except BaseException:
            folder.remove()
            raise
        return UnzippedFolder.attach(raw, folder)


def is_eeglab(path: Path, head: bytes) -> bool:
    """A MATLAB file (an EEGLAB ``.set``), or a zip holding a ``.set``."""
    return head.startswith(EEGLAB_MAGIC) or _zip_holds(path, head, ".set")


# ----------------------------------------------------------------------------- XDF


def _first(value: object, default: object = None) -> object:
    """pyxdf wraps every description value in a list."""
    if isinstance(value, list):
        return value[0] if value else default
    return default if value is None else value


def _stream_label(stream: dict) -> str:
    info = stream["info"]
    return f"{_first(info.get('name'), '?')!r} (type {_first(info.get('type'), '?')})"


def _choose(streams: list[dict], name: str | None, stype: str, shown: str, what: str) -> dict:
    if name is not None:
        found = [s for s in streams if _first(s["info"].get("name")) == name]
        if not found:
            listed = ", ".join(_stream_label(s) for s in streams)
            raise FormatError(f"{shown}: no {what} stream named {name!r}; it has {listed}")
        return found[0]
    found = [s for s in streams if str(_first(s["info"].get("type"), "")).lower() == stype]
    if len(found) != 1:
        listed = ", ".join(_stream_label(s) for s in found or streams)
        raise FormatError(
            f"{shown}: {len(found)} streams of type {stype!r}; name the {what} stream "
            f"(streams: {listed})"
        )
    return found[0]


def _channel_descriptions(stream: dict, shown: str) -> list[dict]:
    desc = _first(stream["info"].get("desc")) or {}
    channels = _first(desc.get("channels") if isinstance(desc, dict) else None) or {}
    entries = channels.get("channel", []) if isinstance(channels, dict) else []
    n = int(_first(stream["info"]["channel_count"]))
    if len(entries) != n:
        raise FormatError(
            f"{shown}: EEG stream {_stream_label(stream)} describes {len(entries)} of its {n} "
            "channels (channel labels are needed to find the ErrP sites)"
        )
    return entries


def _marker_triggers(
    markers: dict, times: np.ndarray, labels: EventLabels
) -> list[tuple[int, int]]:
    """(sample, code) of every action marker inside the EEG stream's time span."""
    out = []
    period = np.median(np.diff(times)) if times.size > 1 else 0.0
    for value, stamp in zip(markers["time_series"], markers["time_stamps"], strict=True):
        text = str(value[0] if isinstance(value, list | tuple | np.ndarray) else value)
        trigger: int | None
        try:
            trigger = ActionMarker.from_lsl(text).trigger or None
        except (ValueError, json.JSONDecodeError):
            trigger = labels.trigger_for(text)
        if trigger is None or not (times[0] - period / 2 <= stamp <= times[-1] + period / 2):
            continue
        out.append((int(np.abs(times - stamp).argmin()), trigger))
    return out


def read_xdf(
    path: Path,
    shown: str,
    labels: EventLabels,
    *,
    stream: str | None = None,
    marker_stream: str | None = None,
) -> mne.io.RawArray:
    """An XDF file's EEG stream as a Raw in volts, with a ``Status`` channel of actions.

    Parameters
    ----------
    stream, marker_stream : str | None
        Names of the EEG and marker streams; default the only stream of type ``EEG``,
        and the only ``Markers`` stream (none: the EEG stream's own ``Status`` channel).

    Channel units come from the description (``microvolts`` when a channel gives none,
    the LSL convention for EEG). Actions are placed on the EEG sample nearest to each
    marker's (clock-synchronised) timestamp; markers outside the EEG stream are dropped.
    """
    import pyxdf

    try:
        streams, _ = pyxdf.load_xdf(str(path), verbose=False)
    except Exception as exc:
        reason = f"{type(exc).__name__}: {exc}"
        raise FormatError(f"{shown}: not a readable XDF file ({reason})") from exc
    eeg = _choose(streams, stream, "eeg", shown, "EEG")
    sfreq = float(_first(eeg["info"]["nominal_srate"]))
    if sfreq <= 0:
        raise FormatError(f"{shown}: EEG stream {_stream_label(eeg)} has no regular rate")
    data = np.asarray(eeg["time_series"], dtype=np.float64)
    times = np.asarray(eeg["time_stamps"], dtype=np.float64)
    if data.ndim != 2 or data.shape[0] < 2:
        raise FormatError(f"{shown}: EEG stream {_stream_label(eeg)} holds no samples")
    effective = (times.size - 1) / (times[-1] - times[0]) if times[-1] > times[0] else 0.0
    if abs(effective / sfreq - 1.0) > MAX_RATE_MISMATCH:
        raise FormatError(
            f"{shown}: EEG stream {_stream_label(eeg)} declares {sfreq:g} Hz but its "
            f"timestamps give {effective:.6g} Hz ({times.size} samples in "
            f"{times[-1] - times[0]:.3f} s): a wrong nominal rate, or samples lost"
        )
    entries = _channel_descriptions(eeg, shown)
    names = [str(_first(entry.get("label"), f"ch{i}")) for i, entry in enumerate(entries)]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise FormatError(
            f"{shown}: EEG stream {_stream_label(eeg)} labels several channels "
            f"{', '.join(repeated[:8])}"
        )
    scale = np.ones(len(names))
    for i, entry in enumerate(entries):
        unit = str(_first(entry.get("unit"), "microvolts")).strip().lower()
        if names[i] != STIM_CHANNEL and unit in _VOLT_SCALE:
            scale[i] = _VOLT_SCALE[unit]
    data = data * scale
    status = np.zeros(data.shape[0])
    if STIM_CHANNEL in names:
        status = data[:, names.index(STIM_CHANNEL)].copy()
        data = np.delete(data, names.index(STIM_CHANNEL), axis=1)
        names.remove(STIM_CHANNEL)
    has_markers = any(str(_first(s["info"].get("type"), "")).lower() == "markers" for s in streams)
    use_markers = marker_stream is not None or has_markers
    if use_markers:
        chosen = _choose(streams, marker_stream, "markers", shown, "marker")
        status = np.zeros(data.shape[0])
        for sample, code in _marker_triggers(chosen, times, labels):
            status[sample] = code
    desc = _first(eeg["info"].get("desc")) or {}
    synthetic = isinstance(desc, dict) and SYNTHETIC_ELEMENT in desc
    info = mne.create_info([*names, STIM_CHANNEL], sfreq, ["misc"] * len(names) + ["stim"])
    if synthetic:
        info["description"] = f"{SYNTHETIC_TAG} ({_first(desc[SYNTHETIC_ELEMENT], '')})"
    raw = mne.io.RawArray(np.vstack([data.T, status[None, :]]), info, verbose="error")
    return raw if use_markers else apply_event_labels(raw, labels)
