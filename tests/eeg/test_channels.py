"""Caps: standard names, per-rig channel maps and the ErrP's required sites."""

from __future__ import annotations

import pytest

from services.eeg.recordings.channels import ChannelError, builtin_channel_map, resolve_channels
from tests.eeg.caps import CAP_8, CAP_32, CAP_64


def test_standard_names_case_insensitive_and_other_channels_kept() -> None:
    names = ["FZ", "fc1", "FC2", "cz", "C3", "C4", "PZ", "oz", "Status", "EXG1"]
    channels = resolve_channels(names)
    assert channels.names == ["Fz", "FC1", "FC2", "Cz", "C3", "C4", "Pz", "Oz", "Status", "EXG1"]
    assert channels.eeg == ["Fz", "FC1", "FC2", "Cz", "C3", "C4", "Pz", "Oz"]
    assert channels.renamed == {"FZ": "Fz", "fc1": "FC1", "cz": "Cz", "PZ": "Pz", "oz": "Oz"}


@pytest.mark.parametrize("cap", [CAP_8, CAP_32, CAP_64], ids=["8", "32", "64"])
def test_caps_of_8_32_64_channels_are_accepted(cap) -> None:
    channels = resolve_channels([*cap, "Status"])
    assert channels.eeg == cap
    assert channels.renamed == {}


def test_rig_map_renames_device_channels() -> None:
    mapping = builtin_channel_map("biosemi64")
    assert len(mapping) == 64
    assert (mapping["A1"], mapping["A32"], mapping["B1"], mapping["B6"]) == (
        "Fp1",
        "CPz",
        "Fpz",
        "Fz",
    )
    device = [*mapping, "EXG1", "Trig"]
    channels = resolve_channels(device, {**mapping, "Trig": "Status"})
    assert channels.eeg == CAP_64
    assert channels.names[-2:] == ["EXG1", "Status"]
    assert builtin_channel_map("biosemi32")["A1"] == "Fp1"
    with pytest.raises(ChannelError, match="no built-in channel map for montage 'biosemi128'"):
        builtin_channel_map("biosemi128")


def test_wrong_and_missing_channels_are_refused_with_the_reason() -> None:
    cyton = ["Fp1", "Fp2", "C3", "C4", "P7", "P8", "O1", "O2"]
    with pytest.raises(
        ChannelError,
        match=r"^cyton: missing the fronto-central sites the ErrP is decoded from: Fz, Cz, "
        r"FCz or FC1 or FC2 \(required: Fz, Cz and one of FCz, FC1, FC2\)$",
    ):
        resolve_channels(cyton, source="cyton")
    with pytest.raises(ChannelError, match=r"missing the .* sites .*: Cz \(required"):
        resolve_channels([c for c in CAP_32 if c != "Cz"])
    with pytest.raises(ChannelError, match=r"rig: 7 channels with standard .* 8 to 256"):
        resolve_channels(CAP_8[:7], source="rig")
    with pytest.raises(
        ChannelError, match=r"the channel map names channels the source does not have: A9"
    ):
        resolve_channels(CAP_8, {"A9": "Fz"})
    with pytest.raises(ChannelError, match=r"no standard 10-20/10-10 name: Fz -> Fzz"):
        resolve_channels(CAP_8, {"Fz": "Fzz"})
    with pytest.raises(ChannelError, match=r"several channels are named \(or mapped to\) Cz"):
        resolve_channels([*CAP_8, "EXG1"], {"EXG1": "cz"})
