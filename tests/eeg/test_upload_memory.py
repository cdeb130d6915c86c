"""Reading a long BrainVision set (markers) or EEGLAB dataset keeps memory bounded: the
``Status`` channel made from its events is one value per sample, and the samples are read
from the files a chunk at a time (issue 25: an upload's peak RSS < 1 GB whatever its
length). Each file is read in a fresh child process, whose peak RSS growth while reading,
validating and counting the actions is compared with the recording's size in float64 (what
loading it costs: the former code loaded it, then copied it to add ``Status``).

Outputs stay bit for bit what they were: tests/eeg/test_formats.py and
test_outside_files.py read the same formats back, and the test below checks the lazily read
samples against MNE's loaded ones."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import mne
import numpy as np
import pytest

from services.eeg.recordings.conventions import STIM_CHANNEL
from services.eeg.recordings.io import action_events, read_recording
from services.eeg.recordings.status_channel import RawWithStatus
from tests.eeg.caps import CAP_8
from tests.eeg.test_formats import CODES, SFREQ, action_samples, write_set, write_vhdr
from tests.helpers import env_without_bgrl

N_CHANNELS, RATE, SECONDS = 32, 1000.0, 240
"""The moderate recording: 32 channels, 4 minutes at 1 kHz: 31 MB as float32 samples, 61 MB
as float64."""
CHUNK_VALUES = 1 << 18
"""Values per chunk the child reads (2 MB of float64; the service's 32 MB would need a long
file to be told from loading it)."""

_WRITE = """
import sys, zipfile
from pathlib import Path
import mne, numpy as np, pybv, scipy.io
folder = Path(sys.argv[1])
n_ch, rate, seconds = int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4])
n = int(rate * seconds)
data = np.random.default_rng(0).standard_normal((n_ch, n), dtype=np.float32) * 2e-5
# the ErrP's fronto-central sites, then other standard 10-05 names
cap = ["Fz", "FCz", "Cz", "FC1", "FC2", "C1", "C2", "CPz"]
pool = [c for c in mne.channels.make_standard_montage("standard_1005").ch_names if c not in cap]
names = (cap + pool)[:n_ch]
onsets = np.arange(2 * int(rate), n - int(rate), int(rate))  # one action a second
codes = [1 + k % 2 for k in range(len(onsets))]
events = [{"onset": int(s), "description": c} for s, c in zip(onsets, codes)]
pybv.write_brainvision(data=data, sfreq=rate, ch_names=names, fname_base="long",
                       folder_out=folder, events=events, unit="V", fmt="binary_float32")
with zipfile.ZipFile(folder / "long.zip", "w") as archive:  # stored: quick to write
    for suffix in ("vhdr", "vmrk", "eeg"):
        archive.write(folder / f"long.{suffix}", f"long.{suffix}")
# EEGLAB as MNE exports it (eeglabio: the samples inside the .set), then as EEGLAB saves by
# default (as in tests/eeg/test_formats.py): the samples (float32, microvolts) in a .fdt
plain = mne.io.RawArray(data, mne.create_info(names, rate, "eeg"), verbose="error")
plain.set_annotations(mne.Annotations(onsets / rate, 0.0, [str(c) for c in codes]))
mne.export.export_raw(folder / "inside.set", plain, fmt="eeglab", verbose="error")
del plain
fields = scipy.io.loadmat(folder / "inside.set")
fields = {key: value for key, value in fields.items() if not key.startswith("__")}
np.asarray(fields["data"], dtype="<f4").T.tofile(folder / "long.fdt")
fields["data"] = fields["datfile"] = "long.fdt"
scipy.io.savemat(folder / "long.set", fields)
print(data.nbytes * 2)
"""

_READ = """
import json, sys
from pathlib import Path
import services.eeg.recordings.bdf as bdf, services.eeg.recordings.io as io
from services.eeg.recordings.io import action_events, read_recording
bdf.CHUNK_VALUES = io.CHUNK_VALUES = int(sys.argv[1])
def resident(field):
    status = Path("/proc/self/status").read_text().splitlines()
    return int(next(line for line in status if line.startswith(field)).split()[1]) * 1024
def read(path):
    raw = read_recording(path)
    return raw, len(action_events(raw))
found = {}
for path in sys.argv[2:]:
    read(path)  # once first: every module a read imports is imported
    before = resident("VmRSS:")
    Path("/proc/self/clear_refs").write_text("5")  # the peak (VmHWM) starts again here
    raw, n_actions = read(path)
    found[Path(path).name] = {"growth_bytes": resident("VmHWM:") - before,
        "n_actions": n_actions, "n_times": int(raw.n_times), "preload": bool(raw.preload)}
    del raw
print(json.dumps(found))
"""


def _python(code: str, *args: str | Path, timeout: float = 180.0) -> str:
    done = subprocess.run(
        [sys.executable, "-c", code, *map(str, args)],
        capture_output=True, text=True, timeout=timeout, env=env_without_bgrl(),
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout.strip().splitlines()[-1]


@pytest.fixture(scope="module")
def long_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    folder = tmp_path_factory.mktemp("long")
    float64_bytes = int(_python(_WRITE, folder, N_CHANNELS, RATE, SECONDS))
    return folder, float64_bytes


def test_a_long_recording_is_read_in_bounded_memory(long_files):
    folder, float64_bytes = long_files
    names = ["long.zip", "long.vhdr", "long.set", "inside.set"]
    found = json.loads(_python(_READ, CHUNK_VALUES, *(folder / name for name in names)))
    for name in names:
        read = found[name]
        assert read["n_times"] == RATE * SECONDS, name
        assert read["n_actions"] == SECONDS - 3, name
        assert read["preload"] is False, name
        # loading it costs float64_bytes (61 MB; the former code: twice that, to add Status);
        # read in chunks of 2 MB, plus Status (8 bytes a sample: 2 MB), it costs a fraction
        assert read["growth_bytes"] < float64_bytes / 3, (name, read, float64_bytes)


def test_status_from_markers_is_read_lazily_with_the_same_samples(tmp_path):
    from tests.eeg.caps import virtual_recording

    raw = virtual_recording(SFREQ, CAP_8, seed=4)
    onsets = action_samples(raw)
    events = [{"onset": int(s), "description": c} for s, c in zip(onsets, CODES, strict=True)]
    vhdr = write_vhdr(raw, tmp_path, events)
    with zipfile.ZipFile(tmp_path / "sub01.zip", "w") as archive:
        for suffix in ("vhdr", "vmrk", "eeg"):
            archive.write(tmp_path / f"sub01.{suffix}", f"sub01.{suffix}")
    split = write_set(raw, tmp_path / "sub02.set", fdt=True)
    loaded = {
        vhdr: mne.io.read_raw_brainvision(vhdr, preload=True, verbose="error"),
        split: mne.io.read_raw_eeglab(split, preload=True, verbose="error"),
    }
    for path, reference in [*loaded.items(), (tmp_path / "sub01.zip", loaded[vhdr])]:
        back = read_recording(path)
        assert isinstance(back, RawWithStatus) and not back.preload
        assert back.ch_names == [*CAP_8, STIM_CHANNEL]
        np.testing.assert_array_equal(back.get_data(picks=CAP_8), reference.get_data())
        np.testing.assert_array_equal(action_events(back)[:, 2], CODES)
        # a window read alone equals the same window of the whole
        np.testing.assert_array_equal(
            back.get_data(start=100, stop=777), back.get_data()[:, 100:777]
        )
        loaded_back = read_recording(path, preload=True)
        np.testing.assert_array_equal(loaded_back.get_data(), back.get_data())
