"""EEG caps: standard 10-20/10-10 channel names, per-rig channel maps, the ErrP's sites.

Any cap with 8 to 256 EEG channels is accepted when it carries the fronto-central sites
the observation ErrP is read from (:data:`REQUIRED_SITES`, and at least one of
:data:`FRONTO_CENTRAL_SITES`). A channel is EEG when its name (after the rig's channel map)
is a standard 10-20/10-10/10-5 position name, compared case-insensitively (``FCZ`` and
``fcz`` are ``FCz``); other channels (``Status``, ``EXG1``, ``AUX``...) are kept but not
decoded.

A rig's channel map ``{device_name: standard_name}`` renames the amplifier's channels
(e.g. BioSemi's ``A1`` ... ``B32``, see :func:`builtin_channel_map`); every device name it
lists must be present, and every target must be a standard name (or ``Status``).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import mne

from services.eeg.recordings.conventions import STIM_CHANNEL

__all__ = [
    "FRONTO_CENTRAL_SITES",
    "MAX_EEG_CHANNELS",
    "MIN_EEG_CHANNELS",
    "REQUIRED_SITES",
    "ChannelError",
    "ChannelSet",
    "builtin_channel_map",
    "resolve_channels",
    "standard_name",
]

MIN_EEG_CHANNELS = 8
MAX_EEG_CHANNELS = 256
REQUIRED_SITES = ("Fz", "Cz")
"""Midline sites every cap must carry (the ErrP's fronto-central maximum lies between them)."""
FRONTO_CENTRAL_SITES = ("FCz", "FC1", "FC2")
"""At least one of these must be present too (FCz is often the reference of 32-channel caps,
which then carry FC1 and FC2)."""
_EDF_SIGNAL_TYPE = "eeg "
"""EDF+ labels start with the signal type (``EEG Fpz-Cz``)."""
_REFERENCE_SUFFIXES = frozenset({"ref", "avg", "ave", "ar", "le"})
"""Suffixes naming a common reference (``Fp1-REF``, ``Cz-AVG``...): the site is monopolar."""
_STANDARD_MONTAGE = "colin27_1005"
"""MNE's 10-5 montage (343 names, a superset of 10-20 and 10-10); bundled, no download."""


class ChannelError(ValueError):
    """A cap or channel map that cannot be used; the message names the channels."""


@functools.cache
def _standard_names() -> dict[str, str]:
    """Lower-case name -> standard spelling, for every 10-5 position name."""
    names = mne.channels.make_standard_montage(_STANDARD_MONTAGE).ch_names
    return {name.lower(): name for name in names}


def standard_name(name: str) -> str | None:
    """The standard spelling of a 10-20/10-10/10-5 name (case-insensitive), else None.

    EDF+ labels are accepted too: the signal type prefix ``EEG `` and a common-reference
    suffix (``-REF``, ``-AVG``, ``-AR``, ``-LE``), e.g. ``EEG Fz-REF`` is ``Fz``; a
    bipolar derivation such as ``Fz-Cz`` is no standard name.
    """
    key = name.strip().lower()
    if key.startswith(_EDF_SIGNAL_TYPE):
        key = key[len(_EDF_SIGNAL_TYPE) :].strip()
    site, dash, reference = key.rpartition("-")
    if dash and reference.strip() in _REFERENCE_SUFFIXES:
        key = site.strip()
    return _standard_names().get(key)


def builtin_channel_map(montage: str) -> dict[str, str]:
    """Device -> standard names of a BioSemi cap recorded with ActiView's ``A1``... names.

    Only the 32- and 64-channel BioSemi layouts are 10-10 positions; the 128/256 layouts
    are radial and have no standard names (give those rigs an explicit map).
    """
    if montage not in ("biosemi32", "biosemi64"):
        raise ChannelError(
            f"no built-in channel map for montage {montage!r}; built-in: biosemi32, biosemi64"
        )
    names = mne.channels.make_standard_montage(montage).ch_names
    device = [f"{bank}{i}" for bank in "AB" for i in range(1, 33)][: len(names)]
    return dict(zip(device, names, strict=True))


@dataclass(frozen=True)
class ChannelSet:
    """The channels of a recording or stream after the rig's map.

    Attributes
    ----------
    names : list of str
        Every channel, in the source's order, renamed: standard EEG names in their standard
        spelling, ``Status`` for the trigger channel, other channels unchanged.
    eeg : list of str
        The EEG channels (standard names), in the source's order.
    renamed : dict
        Source name -> new name, for the channels whose name changed.
    """

    names: list[str]
    eeg: list[str]
    renamed: dict[str, str]


def resolve_channels(
    ch_names: Sequence[str],
    channel_map: Mapping[str, str] | None = None,
    *,
    source: str = "recording",
) -> ChannelSet:
    """Standard names for a source's channels, checked against what the ErrP needs.

    Parameters
    ----------
    ch_names : sequence of str
        The source's channel names, in order.
    channel_map : mapping | None
        Per-rig ``{device_name: standard_name}`` (a target may also be ``Status``).
        Names it does not list are read as standard names case-insensitively.
    source : str
        Name of the source in messages (file name, stream name).

    Raises
    ------
    ChannelError
        A mapped device channel missing from the source, a target that is no standard
        name, two channels with the same standard name, fewer than 8 or more than 256 EEG
        channels, or missing required sites (the message lists them).
    """
    names = list(ch_names)
    mapping = dict(channel_map or {})
    absent = [device for device in mapping if device not in names]
    if absent:
        raise ChannelError(
            f"{source}: the channel map names channels the source does not have: "
            f"{', '.join(absent[:16])}{' ...' if len(absent) > 16 else ''} "
            f"(it has {', '.join(names[:16])}{' ...' if len(names) > 16 else ''})"
        )
    bad_targets = [
        f"{device} -> {target}"
        for device, target in mapping.items()
        if target != STIM_CHANNEL and standard_name(target) is None
    ]
    if bad_targets:
        raise ChannelError(
            f"{source}: channel map targets that are no standard 10-20/10-10 name: "
            f"{', '.join(bad_targets[:16])}"
        )
    out: list[str] = []
    eeg: list[str] = []
    renamed: dict[str, str] = {}
    for name in names:
        target = mapping.get(name, name)
        if target.strip().lower() == STIM_CHANNEL.lower():  # STATUS, status: the trigger
            new = STIM_CHANNEL
        else:
            std = standard_name(target)
            new = std if std is not None else name
            if std is not None:
                eeg.append(std)
        out.append(new)
        if new != name:
            renamed[name] = new
    seen: dict[str, int] = {}
    for new in out:
        seen[new] = seen.get(new, 0) + 1
    duplicates = sorted(name for name, count in seen.items() if count > 1)
    if duplicates:
        raise ChannelError(
            f"{source}: several channels are named (or mapped to) {', '.join(duplicates[:16])}"
        )
    if not MIN_EEG_CHANNELS <= len(eeg) <= MAX_EEG_CHANNELS:
        raise ChannelError(
            f"{source}: {len(eeg)} channels with standard 10-20/10-10 names; "
            f"{MIN_EEG_CHANNELS} to {MAX_EEG_CHANNELS} are needed (give the rig a channel "
            "map when the amplifier names its channels otherwise)"
        )
    missing = [site for site in REQUIRED_SITES if site not in eeg]
    if not any(site in eeg for site in FRONTO_CENTRAL_SITES):
        missing.append(" or ".join(FRONTO_CENTRAL_SITES))
    if missing:
        raise ChannelError(
            f"{source}: missing the fronto-central sites the ErrP is decoded from: "
            f"{', '.join(missing)} (required: {', '.join(REQUIRED_SITES)} and one of "
            f"{', '.join(FRONTO_CENTRAL_SITES)})"
        )
    return ChannelSet(names=out, eeg=eeg, renamed=renamed)
