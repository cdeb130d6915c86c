"""``bgrl subject stream`` without a recording: the virtual subject live over LSL."""

from __future__ import annotations

import time

import typer

from services.eeg.virtual.stream import VirtualLslStream


def stream_virtual_subject(
    *,
    quality: float,
    seed: int,
    sfreq: float,
    name: str,
    marker_stream: str,
    duration_s: float,
) -> None:
    """Stream the virtual subject (SYNTHETIC) in real time until Ctrl-C or ``duration_s``.

    Every marker of ``marker_stream`` drives the subject: an ErrP after an error.
    """
    stream = VirtualLslStream(
        quality=quality, seed=seed, sfreq=sfreq, name=name, marker_stream=marker_stream
    )
    typer.echo(
        f"streaming the virtual subject (SYNTHETIC, quality {quality:g}, seed {seed}, "
        f"{sfreq:g} Hz) as LSL stream {name!r}, following markers of {marker_stream!r}"
    )
    start = time.monotonic()
    try:
        with stream:
            while duration_s <= 0 or time.monotonic() - start < duration_s:
                time.sleep(0.2)
                if stream.error is not None:
                    raise typer.Exit(code=1)
    except KeyboardInterrupt:
        pass
    finally:
        typer.echo(
            f"stopped: {stream.n_pushed} samples, {stream.markers_received} markers"
            + (f", {stream.source.late_markers} late" if stream.source.late_markers else "")
            + (f"; error: {stream.error}" if stream.error else "")
        )
