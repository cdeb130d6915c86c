"""``bgrl eeg ...`` (calibration, quality sweep) and ``bgrl bench eeg``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from services.cli.paths import output_folder, refuse_file
from services.eeg.training_config import DECODERS

eeg_app = typer.Typer(help="ErrP decoding: calibrate classifiers, sweep subject quality.")


@eeg_app.command("calibrate")
def calibrate_command(
    recording: Annotated[
        Path,
        typer.Argument(
            help="Calibration recording: BDF, EDF, FIF, XDF, BrainVision .vhdr (its .vmrk "
            "and .eeg beside it) or a zip of those three, EEGLAB .set (its .fdt beside it) "
            "or a zip of the two."
        ),
    ],
    out: Annotated[Path, typer.Option(help="Folder for the classifier, metrics and report.")],
    channel_map: Annotated[
        Path | None,
        typer.Option(
            help="JSON file {device_channel: standard_name} of the rig (e.g. BioSemi A1..B32)."
        ),
    ] = None,
    event_label: Annotated[
        list[str] | None,
        typer.Option(
            "--event-label",
            help="KEY=correct|error (repeatable; replaces the defaults 1/2 and "
            "'correct'/'error'): a Status code or an annotation/marker text.",
        ),
    ] = None,
    stream: Annotated[str | None, typer.Option(help="XDF: name of the EEG stream.")] = None,
    marker_stream: Annotated[
        str | None, typer.Option(help="XDF: name of the marker stream.")
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, help="Seed of the split, initialisation and batches.")
    ] = 0,
    max_passes: Annotated[
        int,
        typer.Option(min=1, help="Upper bound on training passes (early stopping may end sooner)."),
    ] = 300,
    decoders: Annotated[
        str,
        typer.Option(
            help="Comma-separated decoders trained on the same split (eegnet, lda, "
            "xdawn_rg); the best on validation is kept."
        ),
    ] = ",".join(DECODERS),
    report: Annotated[bool, typer.Option(help="Write report.png / report.html.")] = True,
    onnx: Annotated[
        bool, typer.Option(help="Also export model.onnx (EEGNet, sLDA; xDAWN + RG has none).")
    ] = True,
) -> None:
    """Train and evaluate the ErrP classifier on RECORDING; writes OUT/metrics.json."""
    import torch

    from services.eeg.calibration import TrainingConfig, calibrate
    from services.eeg.io import RecordingError, read_recording

    torch.set_num_threads(1)  # this process only: one core, bit-reproducible runs
    try:
        names = tuple(d.strip() for d in decoders.split(",") if d.strip())
        config = TrainingConfig(max_passes=max_passes, decoders=names)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--decoders") from exc
    refuse_file(out)
    mapping = _read_channel_map(channel_map) if channel_map is not None else None
    labels = _event_labels(event_label) if event_label else None
    try:
        raw = read_recording(
            recording,
            channel_map=mapping,
            labels=labels,
            xdf_stream=stream,
            xdf_marker_stream=marker_stream,
        )
    except (RecordingError, FileNotFoundError) as exc:
        raise typer.BadParameter(str(exc), param_hint="RECORDING") from exc
    try:
        result = calibrate(
            raw,
            seed=seed,
            out_dir=out,
            config=config,
            report=report,
            onnx=onnx,
            progress=True,
        )
    except ValueError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from exc
    m = result.metrics
    tag = " [SYNTHETIC data]" if m["synthetic"] else ""
    for name, d in m["decoders"].items():
        kept = " (kept)" if name == m["decoder"] else ""
        typer.echo(
            f"{name}{kept}: validation accuracy {d['val_accuracy']:.3f}, "
            f"test accuracy {d['test_accuracy']:.3f}"
        )
    typer.echo(
        f"test accuracy {m['test_accuracy']:.3f}, balanced {m['balanced_accuracy']:.3f}, "
        f"ROC AUC {m['roc_auc']:.3f} on {m['n_test']} of {m['n_epochs']} epochs{tag}"
    )
    typer.echo(f"wrote {out / 'metrics.json'}")


def _read_channel_map(path: Path) -> dict[str, str]:
    """A rig's channel map from a JSON object file; ``BadParameter`` naming the problem."""
    try:
        mapping = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise typer.BadParameter(f"{path.name}: {exc}", param_hint="--channel-map") from exc
    if not isinstance(mapping, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in mapping.items()
    ):
        raise typer.BadParameter(
            f"{path.name}: expected a JSON object of channel names", param_hint="--channel-map"
        )
    return mapping


def _event_labels(pairs: list[str]):
    """``EventLabels`` from ``KEY=correct|error`` pairs (an integer KEY is a Status code)."""
    from services.eeg.formats import EventLabels

    codes: dict[int, str] = {}
    descriptions: dict[str, str] = {}
    for pair in pairs:
        key, sep, label = pair.rpartition("=")
        if not sep or not key or label not in ("correct", "error"):
            raise typer.BadParameter(
                f"{pair!r}: expected KEY=correct or KEY=error", param_hint="--event-label"
            )
        if key.strip().isdigit():
            codes[int(key)] = label
        else:
            descriptions[key] = label
    return EventLabels(codes=codes, descriptions=descriptions)


@eeg_app.command("quality-sweep")
def quality_sweep_command(
    out: Annotated[Path, typer.Option(help="Folder for quality_sweep.json, .csv and .png.")] = Path(
        "benchmarks/results"
    ),
    qualities: Annotated[
        list[float] | None,
        typer.Option(
            "--quality",
            min=0.0,
            help="Quality levels (repeatable); above 1 extrapolates the generator's ErrP.",
        ),
    ] = None,
    seeds: Annotated[int, typer.Option(min=1, help="Subjects (seeds) per quality level.")] = 5,
    actions: Annotated[int, typer.Option(min=60, help="Actions per calibration session.")] = 600,
    error_rate: Annotated[float, typer.Option(min=0.05, max=0.95)] = 0.3,
    max_passes: Annotated[int, typer.Option(min=1, help="Training passes cap per run.")] = 150,
    jobs: Annotated[int, typer.Option(min=1, help="Worker processes.")] = 1,
    decoders: Annotated[
        str,
        typer.Option(
            help="Comma-separated decoders trained on each split (eegnet, lda, xdawn_rg)."
        ),
    ] = ",".join(DECODERS),
) -> None:
    """Simulate and calibrate virtual subjects per quality level: every decoder on the same
    splits; writes quality_sweep.json, .csv and .png and prints the table."""
    from benchmarks.bench_eeg import (
        DEFAULT_QUALITIES,
        format_sweep_table,
        quality_sweep,
        write_sweep_outputs,
    )
    from services.eeg.calibration import TrainingConfig

    names = tuple(d.strip() for d in decoders.split(",") if d.strip())
    try:
        TrainingConfig(decoders=names)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--decoders") from exc
    output_folder(out)
    result = quality_sweep(
        qualities or list(DEFAULT_QUALITIES),
        n_seeds=seeds,
        n_actions=actions,
        error_rate=error_rate,
        max_passes=max_passes,
        jobs=jobs,
        partial_path=out / "quality_sweep.partial.json",
        decoders=names,
    )
    paths = write_sweep_outputs(result, out)
    typer.echo(format_sweep_table(result))
    typer.echo("wrote " + ", ".join(str(p) for p in paths))


def bench_eeg(
    out: Annotated[Path, typer.Option(help="Folder for eeg.json.")] = Path("benchmarks/results"),
    actions: Annotated[int, typer.Option(min=10, help="Actions in the live LSL replay.")] = 500,
    speed: Annotated[float, typer.Option(min=0.5, help="Replay speed (x real time).")] = 3.0,
    minutes: Annotated[
        float, typer.Option(min=0.5, help="Recording length for the offline and memory figures.")
    ] = 20.0,
    memory_only: Annotated[
        bool,
        typer.Option(
            "--memory-only", help="Only the peak-memory figures (writes eeg_memory.json)."
        ),
    ] = False,
) -> None:
    """Peak memory of simulate / calibrate / service reading, decision latency (live LSL
    replay), offline preprocessing speed, training time."""
    from benchmarks.bench_eeg import bench_memory, run_benchmark
    from services.core.files import finite_or_null, write_results_json

    output_folder(out)
    if memory_only:
        memory = bench_memory(minutes)
        path = write_results_json(out / "eeg_memory.json", memory)
        typer.echo(json.dumps(finite_or_null(memory), indent=2))
        typer.echo(f"wrote {path}")
        return
    result = run_benchmark(n_actions=actions, speed=speed, offline_minutes=minutes)
    path = write_results_json(out / "eeg.json", result)
    typer.echo(json.dumps(result["summary"], indent=2))
    typer.echo(f"wrote {path}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl eeg`` and ``bgrl bench eeg``."""
    app.add_typer(eeg_app, name="eeg")
    bench_app.command("eeg")(bench_eeg)
