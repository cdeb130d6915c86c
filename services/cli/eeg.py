"""``bgrl eeg ...``: calibration and the bits per label (the quality sweep and ``bgrl bench
eeg`` are :mod:`benchmarks.commands`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from services.cli.paths import output_folder, refuse_file
from services.eeg.decoding.training_config import DECODERS

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

    from services.eeg.decoding.calibration import TrainingConfig, calibrate
    from services.eeg.recordings.io import RecordingError, read_recording

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
    from services.eeg.recordings.formats import EventLabels

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


@eeg_app.command("information")
def information_command(
    out: Annotated[Path, typer.Option(help="Folder for information.json and information.md.")],
    targets: Annotated[
        str, typer.Option(help="Comma-separated target held-out accuracies of the decoder.")
    ] = "0.55,0.6,0.65,0.7,0.8",
    seeds: Annotated[
        int, typer.Option(min=1, help="Virtual subjects (seeds FIRST_SEED..FIRST_SEED+n-1).")
    ] = 3,
    first_seed: Annotated[
        int,
        typer.Option(
            min=0, help="Seed of the first virtual subject (confirmatory runs: 1000, fresh)."
        ),
    ] = 0,
    decoders: Annotated[
        str,
        typer.Option(
            help="Decoders each calibration trains (eegnet,lda,xdawn_rg); EEGNet costs ~1 min "
            "of CPU per calibration and the quality search calibrates ~5 times per target."
        ),
    ] = "lda",
    epochs: Annotated[
        int, typer.Option(min=200, help="Fresh held-out epochs per subject (half errors).")
    ] = 4000,
) -> None:
    """Bits per label of the hard and the soft channel on the virtual subject (SYNTHETIC).

    For each subject and target accuracy the subject's quality is found (bisection, cached
    in OUT/virtual_subjects as for `bgrl reproduce --feedback virtual_subject`), its decoder
    calibrated on its own 600-action session, and on a separate session of fresh epochs:
    the hard channel's 1 - H(error rate) and I(decision; truth), the soft channel's
    I(calibrated posterior; truth) with a bootstrap 95 % interval, the Gaussian-score
    reference, and the subject's trial-to-trial ErrP variability at FCz.
    """
    from services.cli.feedback_options import FEEDBACK_CACHE
    from services.core.files import write_results_json
    from services.eeg.decoding.calibration import TrainingConfig
    from services.worker.label_information import format_table, measure_subject, summarize

    names = tuple(d.strip() for d in decoders.split(",") if d.strip())
    try:
        config = TrainingConfig(decoders=names)
        target_list = [float(t) for t in targets.split(",") if t.strip()]
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if not target_list or not all(0.5 < t < 1.0 for t in target_list):
        raise typer.BadParameter("targets must lie in (0.5, 1)", param_hint="--targets")
    output_folder(out)
    rows = []
    for seed in range(first_seed, first_seed + seeds):
        rows.extend(
            measure_subject(
                seed, target_list, config, cache_dir=str(out / FEEDBACK_CACHE), n_epochs=epochs
            )
        )
        write_results_json(out / "information.json", {"rows": rows, "decoders": list(names)})
    summary = summarize(rows)
    table = format_table(summary)
    write_results_json(
        out / "information.json", {"rows": rows, "summary": summary, "decoders": list(names)}
    )
    (out / "information.md").write_text(table + "\n")
    typer.echo(table)
    typer.echo(f"wrote {out / 'information.json'} and information.md")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``bgrl eeg`` (its quality sweep: benchmarks.commands)."""
    app.add_typer(eeg_app, name="eeg")
