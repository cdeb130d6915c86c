"""Calibration report: ErrP grand averages, topographies, training curves, confusion matrix,
and the reliability diagram of the calibrated P(error) (:mod:`services.eeg.decoding.posterior`).

Writes ``report.png`` and a small ``report.html`` (metrics table + the figure). Figures are
drawn with matplotlib's Agg canvas (no display needed). Reports of virtual-subject data say
SYNTHETIC in the title and in the page.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

if TYPE_CHECKING:
    from services.eeg.decoding.result import CalibrationResult
    from services.eeg.recordings.epochs import EpochSet

REPORT_PNG = "report.png"
REPORT_HTML = "report.html"
WAVEFORM_CHANNELS = ("FCz", "Cz")
DECODER_NAMES = {"eegnet": "EEGNet", "lda": "window-mean sLDA", "xdawn_rg": "xDAWN + RG"}
"""Display names of the decoders (services.eeg.decoding.training_config.DECODERS)."""
DECODER_COLORS = {"eegnet": "C2", "lda": "C4", "xdawn_rg": "C1"}


def difference_wave(epochs: EpochSet, channel: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grand averages in microvolts at ``channel``: (error, correct, error - correct)."""
    i = epochs.ch_names.index(channel)
    error = epochs.X[epochs.y == 1, i].mean(axis=0) * 1e6
    correct = epochs.X[epochs.y == 0, i].mean(axis=0) * 1e6
    return error, correct, error - correct


def _epoch_times(epochs: EpochSet) -> np.ndarray:
    p = epochs.params
    return (round(p.tmin * p.sfreq_out) + np.arange(p.n_times_epoch)) / p.sfreq_out


def _topomap_info(epochs: EpochSet):
    """MNE Info with the biosemi64 montage, or None if the channels are not all in it."""
    import mne

    montage = mne.channels.make_standard_montage("biosemi64")
    if not set(epochs.ch_names) <= set(montage.ch_names):
        return None
    info = mne.create_info(epochs.ch_names, epochs.params.sfreq_out, "eeg")
    info.set_montage(montage)
    return info


def draw_report(result: CalibrationResult) -> Figure:
    """The calibration report figure (2 x 4 panels)."""
    import mne

    epochs, metrics, history = result.epochs, result.metrics, result.history
    times_ms = _epoch_times(epochs) * 1e3
    fig = Figure(figsize=(20, 8.5), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 4)
    tag = "SYNTHETIC (virtual subject) - " if epochs.synthetic else ""
    kept = DECODER_NAMES.get(metrics.get("decoder", "eegnet"), "EEGNet")
    fig.suptitle(
        f"{tag}ErrP calibration ({kept} kept): test accuracy "
        f"{metrics['test_accuracy']:.2f}, balanced {metrics['balanced_accuracy']:.2f}, "
        f"ROC AUC {metrics['roc_auc']:.2f} "
        f"({metrics['n_epochs']} epochs, {int(np.sum(epochs.y))} errors)"
    )
    channels = [c for c in WAVEFORM_CHANNELS if c in epochs.ch_names]
    ax = axes[0, 0]
    diff_ref = None
    for channel, color in zip(channels, ("C0", "C3"), strict=False):
        error, correct, diff = difference_wave(epochs, channel)
        ax.plot(times_ms, diff, color=color, lw=2, label=f"{channel} error - correct")
        ax.plot(times_ms, error, color=color, lw=0.8, ls="--", label=f"{channel} error")
        ax.plot(times_ms, correct, color=color, lw=0.8, ls=":", label=f"{channel} correct")
        diff_ref = diff if diff_ref is None else diff_ref
    ax.axhline(0, color="k", lw=0.5)
    ax.set(xlabel="time after action (ms)", ylabel="µV", title="Grand average (causal 1-40 Hz)")
    ax.legend(fontsize=7)

    info = _topomap_info(epochs)
    diff_all = (epochs.X[epochs.y == 1].mean(0) - epochs.X[epochs.y == 0].mean(0)) * 1e6
    for ax, pick in zip(axes[0, 1:3], (np.argmin, np.argmax), strict=True):
        if info is None or diff_ref is None:
            ax.axis("off")
            ax.text(0.5, 0.5, "no topography: channels not in biosemi64", ha="center")
            continue
        k = int(pick(diff_ref))
        values = diff_all[:, k]
        lim = float(np.abs(values).max()) or 1.0
        im, _ = mne.viz.plot_topomap(
            values, info, axes=ax, show=False, cmap="RdBu_r", vlim=(-lim, lim)
        )
        fig.colorbar(im, ax=ax, shrink=0.7, label="µV")
        kind = "negative" if pick is np.argmin else "positive"
        ax.set_title(f"Error - correct at {kind} peak ({times_ms[k]:.0f} ms)")

    ax = axes[1, 0]
    passes = np.arange(1, len(history["train_loss"]) + 1)
    if passes.size:
        ax.plot(passes, history["train_loss"], label="train loss")
        ax.plot(passes, history["val_loss"], label="validation loss")
        ax.axvline(metrics["best_pass"] + 1, color="k", ls="--", lw=0.8, label="kept pass")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "EEGNet not trained", ha="center", transform=ax.transAxes)
    ax.set(xlabel="training pass", ylabel="weighted cross-entropy", title="EEGNet training")
    ax = axes[1, 1]
    if passes.size:
        ax.plot(passes, history["val_accuracy"], color=DECODER_COLORS["eegnet"], label="EEGNet")
    for name, row in metrics.get("decoders", {}).items():
        if name != "eegnet":
            ax.axhline(
                row["val_accuracy"], color=DECODER_COLORS[name], ls="--", label=DECODER_NAMES[name]
            )
    ax.legend(fontsize=8)
    ax.set(
        xlabel="training pass",
        ylabel="accuracy",
        title=f"Validation accuracy ({kept} kept)",
        ylim=(0, 1),
    )

    ax = axes[1, 2]
    cm = np.asarray(metrics["confusion_matrix"])
    ax.imshow(cm, cmap="Blues")
    for (r, c), v in np.ndenumerate(cm):
        ax.text(c, r, str(v), ha="center", va="center", fontsize=14)
    ax.set(
        xticks=[0, 1],
        yticks=[0, 1],
        xticklabels=["correct", "error"],
        yticklabels=["correct", "error"],
        xlabel="predicted",
        ylabel="true",
        title=f"Test confusion matrix (n={cm.sum()})",
    )
    _draw_reliability(axes[0, 3], axes[1, 3], result)
    return fig


def _draw_reliability(diagram, histogram, result: CalibrationResult) -> None:
    """Reliability diagram (raw and calibrated P(error) on the test epochs) and the
    calibrated posterior's histogram per true class."""
    calibration = result.metrics.get("calibration")
    if calibration is None or result.classifier.calibration is None:
        for ax in (diagram, histogram):
            ax.axis("off")
            ax.text(0.5, 0.5, "no posterior calibration", ha="center")
        return
    diagram.plot([0, 1], [0, 1], color="k", lw=0.6, ls=":", label="perfectly calibrated")
    for key, label, color in (
        ("test_reliability_raw", f"raw (ECE {calibration['test_ece_raw']:.3f})", "C7"),
        ("test_reliability", f"calibrated (ECE {calibration['test_ece']:.3f})", "C3"),
    ):
        rows = calibration[key]
        diagram.plot(
            [r["mean_p_error"] for r in rows],
            [r["error_fraction"] for r in rows],
            "o-",
            color=color,
            label=label,
        )
    diagram.set(
        xlabel="predicted P(error)",
        ylabel="fraction of errors",
        xlim=(0, 1),
        ylim=(0, 1),
        title=f"Reliability on the test epochs (Platt fit on {calibration['n_fit']} validation)",
    )
    diagram.legend(fontsize=7)
    y_test = result.epochs.y[result.split.test]
    posterior = result.classifier.calibration.posterior(result.test_proba)
    bins = np.linspace(0, 1, 11)
    histogram.hist(posterior[y_test == 0], bins=bins, alpha=0.6, label="correct", color="C0")
    histogram.hist(posterior[y_test == 1], bins=bins, alpha=0.6, label="error", color="C3")
    histogram.set(
        xlabel="calibrated P(error | epoch)", ylabel="test epochs", title="Calibrated posterior"
    )
    histogram.legend(fontsize=8)


def write_report(result: CalibrationResult, out_dir: str | Path) -> tuple[Path, Path]:
    """Write ``report.png`` and ``report.html`` to ``out_dir``; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    png, page = out / REPORT_PNG, out / REPORT_HTML
    draw_report(result).savefig(png, dpi=90)
    m = result.metrics
    keys = (
        "decoder",
        "test_accuracy",
        "balanced_accuracy",
        "roc_auc",
        "n_epochs",
        "n_train",
        "n_val",
        "n_test",
        "error_fraction",
        "n_params",
        "best_pass",
        "passes_run",
        "train_seconds",
        "seed",
    )
    calibration = m.get("calibration") or {}
    posterior_rows = "".join(
        f"<tr><th>{label}</th><td>{calibration[k]:.3f}</td></tr>"
        for k, label in (
            ("slope", "Platt slope"),
            ("intercept", "Platt intercept"),
            ("test_ece_raw", "test ECE, raw P(error)"),
            ("test_ece", "test ECE, calibrated"),
        )
        if isinstance(calibration.get(k), float)
    )
    rows = "\n".join(
        f"<tr><th>{k}</th><td>{v:.3f}</td></tr>"
        if isinstance(v, float)
        else f"<tr><th>{k}</th><td>{html.escape(str(v))}</td></tr>"
        for k in keys
        if (v := m.get(k)) is not None
    )
    decoder_rows = "\n".join(
        f"<tr><td>{html.escape(DECODER_NAMES[name])}{' (kept)' if name == m.get('decoder') else ''}"
        f"</td><td>{d['val_accuracy']:.3f}</td><td>{d['test_accuracy']:.3f}</td>"
        f"<td>{d['balanced_accuracy']:.3f}</td><td>{d['roc_auc']:.3f}</td>"
        f"<td>{d['n_params']}</td><td>"
        + (f"{d['cv_accuracy_mean']:.3f} ± {d['cv_accuracy_std']:.3f}" if "cv_folds" in d else "-")
        + "</td></tr>"
        for name, d in m.get("decoders", {}).items()
    )
    decoders = (
        "<h2>Decoders (same split; the better on validation is kept)</h2><table><tr>"
        "<th>decoder</th><th>validation accuracy</th><th>test accuracy</th>"
        "<th>balanced accuracy</th><th>ROC AUC</th><th>parameters</th>"
        f"<th>5-fold CV accuracy (training split)</th></tr>{decoder_rows}</table>"
    )
    banner = (
        '<p style="color:#b00;font-weight:bold">SYNTHETIC data (virtual subject), not a '
        "real recording.</p>"
        if result.epochs.synthetic
        else ""
    )
    page.write_text(
        "<!doctype html><html><head><meta charset='utf-8'><title>ErrP calibration report"
        f"</title></head><body><h1>ErrP calibration report</h1>{banner}"
        f"<table>{rows}{posterior_rows}</table>{decoders}"
        "<p>Confusion matrix (rows true, columns predicted; "
        f"correct, error): {html.escape(str(m['confusion_matrix']))}</p>"
        f"<img src='{REPORT_PNG}' alt='calibration report figure' style='max-width:100%'>"
        "</body></html>"
    )
    return png, page
