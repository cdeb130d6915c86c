"""Zipped recordings are checked before anything is unzipped (the audit's finding 1: a 2 MB
BrainVision zip of a 2 GiB ``.eeg`` of zeros took the EEG service from 384 MiB to 4.5 GiB
and wrote 2 GiB to disk)."""

from __future__ import annotations

import gc
import struct
import tempfile
import zipfile
from pathlib import Path

import mne
import pytest
from fastapi.testclient import TestClient

from services.eeg.recordings.io import RecordingError, read_recording
from services.eeg.service.app import create_app
from services.eeg.service.settings import EEGSettings
from tests.eeg.caps import CAP_8, LABELS, virtual_recording
from tests.eeg.test_formats import CODES, SFREQ, action_samples, write_vhdr

FRAME = len(CAP_8) * 4  # pybv writes float32 samples


@pytest.fixture(scope="module")
def raw() -> mne.io.RawArray:
    return virtual_recording(SFREQ, CAP_8, seed=4)


def _set(raw: mne.io.BaseRaw, folder: Path) -> list[Path]:
    events = [
        {"onset": int(s), "description": c} for s, c in zip(action_samples(raw), CODES, strict=True)
    ]
    write_vhdr(raw, folder, events)
    return sorted(folder.glob("sub01.*"))


def zip_files(files: list[Path], path: Path) -> Path:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for file in files:
            archive.write(file, file.name)
    return path


@pytest.fixture
def no_temp_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Temporary folders go to a folder of the test, checked empty afterwards."""
    folder = tmp_path / "temp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def _bomb(raw: mne.io.BaseRaw, folder: Path) -> Path:
    """A valid header and markers with a ``.eeg`` of zeros (a moderate 24 MiB here; the
    audit's was 2 GiB): about a thousand times its zipped size."""
    files = _set(raw, folder)
    eeg = next(file for file in files if file.suffix == ".eeg")
    n_bytes = 24 << 20  # past RATIO_FREE_BYTES
    eeg.write_bytes(bytes(n_bytes - n_bytes % FRAME))
    return zip_files(files, folder / "bomb.zip")


def test_a_zip_bomb_is_refused_before_it_is_unzipped(raw, tmp_path, no_temp_files):
    bomb = _bomb(raw, tmp_path)
    assert bomb.stat().st_size < 100_000
    with pytest.raises(RecordingError, match=r"^bomb\.zip: sub01\.eeg would unzip to .*zip bomb"):
        read_recording(bomb)
    assert list(no_temp_files.iterdir()) == []  # nothing was unzipped


def _declare_size(path: Path, member: str, size: int) -> None:
    """Make the zip's headers (local and central) claim ``size`` unzipped bytes for
    ``member``, as a crafted zip does."""
    data = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as archive:
        local = archive.getinfo(member).header_offset
    struct.pack_into("<I", data, local + 22, size)
    central = data.find(b"PK\x01\x02")
    while central != -1:
        name_length = struct.unpack_from("<H", data, central + 28)[0]
        if data[central + 46 : central + 46 + name_length] == member.encode():
            struct.pack_into("<I", data, central + 24, size)
            break
        central = data.find(b"PK\x01\x02", central + 4)
    path.write_bytes(bytes(data))


def test_a_member_declaring_a_huge_size_is_refused_unread(raw, tmp_path, no_temp_files):
    archive = zip_files(_set(raw, tmp_path), tmp_path / "liar.zip")
    huge = (3 << 30) - (3 << 30) % FRAME  # 3 GiB, a whole number of samples
    _declare_size(archive, "sub01.eeg", huge)
    with zipfile.ZipFile(archive) as opened:
        assert opened.getinfo("sub01.eeg").file_size == huge
    with pytest.raises(RecordingError, match=rf"^liar\.zip: sub01\.eeg would unzip to {huge} "):
        read_recording(archive)
    assert list(no_temp_files.iterdir()) == []


def test_a_samples_file_that_does_not_fit_its_header_is_refused_unread(
    raw, tmp_path, no_temp_files
):
    files = _set(raw, tmp_path)
    eeg = next(file for file in files if file.suffix == ".eeg")
    eeg.write_bytes(eeg.read_bytes() + b"\x00" * 3)  # no whole sample
    archive = zip_files(files, tmp_path / "odd.zip")
    with pytest.raises(RecordingError, match=r"^odd\.zip: truncated: the \.eeg file ends inside"):
        read_recording(archive)
    assert list(no_temp_files.iterdir()) == []


def test_the_eeg_service_refuses_a_zip_bomb_upload_and_keeps_nothing(raw, tmp_path):
    bomb = _bomb(raw, tmp_path)
    data = tmp_path / "data"
    with TestClient(create_app(EEGSettings(data_dir=data))) as client:
        response = client.post("/recordings", files={"file": ("bomb.zip", bomb.read_bytes())})
    assert response.status_code == 422
    assert "zip bomb" in response.json()["detail"]
    left = [p for p in data.rglob("*") if p.is_file()]
    assert all(p.stat().st_size < 1 << 20 for p in left), left
    assert not [p for p in left if p.suffix in (".brainvision", ".part", ".zip")]


def test_a_well_formed_zip_still_reads(raw, tmp_path, no_temp_files):
    """Its samples are read from the unzipped files as long as the recording (or a copy of
    it) exists; the files go with the last of them."""
    back = read_recording(zip_files(_set(raw, tmp_path), tmp_path / "good.zip"))
    assert back.n_times == raw.n_times and len(LABELS) > 0
    (unzipped,) = no_temp_files.iterdir()
    copy = back.copy()
    del back
    gc.collect()
    assert copy.get_data().shape == (len(CAP_8) + 1, raw.n_times)
    del copy
    gc.collect()
    assert not unzipped.exists()
    assert list(no_temp_files.iterdir()) == []
