"""A minimal XDF writer for tests (pyxdf reads XDF but ships no writer).

Follows the XDF 1.0 specification (https://github.com/sccn/xdf/wiki/Specifications):
the magic ``XDF:``, then chunks ``[NumLengthBytes][Length][Tag][Content]`` with a
FileHeader (tag 1), a StreamHeader (2) per stream, Samples (3), ClockOffset (4) and a
StreamFooter (6) per stream. Numeric samples are little-endian, each with its own
timestamp; string samples are ``[NumLengthBytes][Length][bytes]``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np


@dataclass
class XdfStream:
    """One stream to write: numeric (``values`` n x channels) or string markers."""

    name: str
    stype: str
    timestamps: np.ndarray
    values: np.ndarray | list[str]
    nominal_srate: float = 0.0
    channels: list[dict[str, str]] = field(default_factory=list)
    extra_desc: str = ""


def _varlen(n: int) -> bytes:
    if n < 256:
        return struct.pack("<BB", 1, n)
    if n < 1 << 32:
        return struct.pack("<BI", 4, n)
    return struct.pack("<BQ", 8, n)


def _chunk(tag: int, content: bytes) -> bytes:
    return _varlen(len(content) + 2) + struct.pack("<H", tag) + content


def _header_xml(stream: XdfStream, stream_id: int) -> bytes:
    is_string = isinstance(stream.values, list)
    n_channels = 1 if is_string else stream.values.shape[1]
    channels = "".join(
        "<channel>" + "".join(f"<{k}>{escape(v)}</{k}>" for k, v in ch.items()) + "</channel>"
        for ch in stream.channels
    )
    return (
        '<?xml version="1.0"?><info>'
        f"<name>{escape(stream.name)}</name><type>{escape(stream.stype)}</type>"
        f"<channel_count>{n_channels}</channel_count>"
        f"<nominal_srate>{stream.nominal_srate}</nominal_srate>"
        f"<channel_format>{'string' if is_string else 'float32'}</channel_format>"
        f"<source_id>test-{stream_id}</source_id><version>1.1</version>"
        f"<created_at>0</created_at><uid>uid-{stream_id}</uid>"
        "<session_id>default</session_id><hostname>test</hostname>"
        f"<desc><channels>{channels}</channels>{stream.extra_desc}</desc></info>"
    ).encode()


def _samples(stream: XdfStream) -> bytes:
    parts = [_varlen(len(stream.timestamps))]
    for i, stamp in enumerate(stream.timestamps):
        parts.append(struct.pack("<Bd", 8, float(stamp)))
        if isinstance(stream.values, list):
            text = stream.values[i].encode()
            parts.append(_varlen(len(text)) + text)
        else:
            parts.append(np.asarray(stream.values[i], dtype="<f4").tobytes())
    return b"".join(parts)


def write_xdf(path: Path, streams: list[XdfStream]) -> Path:
    """Write ``streams`` to ``path`` as an XDF file LabRecorder could have made."""
    out = [b"XDF:", _chunk(1, b'<?xml version="1.0"?><info><version>1.0</version></info>')]
    for sid, stream in enumerate(streams, start=1):
        out.append(_chunk(2, struct.pack("<I", sid) + _header_xml(stream, sid)))
    for sid, stream in enumerate(streams, start=1):
        out.append(_chunk(3, struct.pack("<I", sid) + _samples(stream)))
        for when in (stream.timestamps[:1], stream.timestamps[-1:]):
            if len(when):
                out.append(_chunk(4, struct.pack("<Idd", sid, float(when[0]), 0.0)))
    for sid, stream in enumerate(streams, start=1):
        first, last = stream.timestamps[0], stream.timestamps[-1]
        footer = (
            '<?xml version="1.0"?><info>'
            f"<first_timestamp>{first}</first_timestamp><last_timestamp>{last}</last_timestamp>"
            f"<sample_count>{len(stream.timestamps)}</sample_count></info>"
        )
        out.append(_chunk(6, struct.pack("<I", sid) + footer.encode()))
    path.write_bytes(b"".join(out))
    return path
