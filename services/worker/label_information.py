"""Bits per label of the hard and the soft channel, measured on the virtual subject end to end.

For each subject (seed) and target decoding accuracy: the subject's quality is found as for
an end-to-end run (:func:`~services.worker.e2e_feedback.find_quality`, the same cache), its
decoder calibrated on its own 600-action calibration session, and the information of one
label measured on a separate session of fresh epochs, half of them errors
(:mod:`services.eeg.decoding.information`): the hard channel's ``1 - H(error rate)`` and the mutual
information of the decisions with the truth, the soft channel's mutual information of the
calibrated posterior with the truth (binned, bootstrap interval), and the Gaussian-score
reference at the same accuracy. Beside them, the subject's trial-to-trial variability at
FCz: the ErrP's amplitude at its negative peak, its SD over error trials (the generator's
amplitude and latency jitter) and the single-trial signal-to-noise ratio with the background.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.eeg.decoding.information import (
    bootstrap_interval,
    gaussian_reference,
    hard_bits,
    plugin_information,
    soft_bin_edges,
    soft_information,
)
from services.eeg.decoding.posterior import PosteriorCalibration
from services.eeg.decoding.training_config import TrainingConfig
from services.worker.e2e_feedback import (
    SubjectEpochs,
    SubjectRecording,
    calibrate_subject,
    find_quality,
)

INFORMATION_SESSION = 4
"""The subject's session the information is measured on (not calibrated or searched on)."""
INFORMATION_EPOCHS = 4000
VARIABILITY_CHANNEL = "FCz"


@dataclass
class InformationSession:
    """Epochs of the information session at quality 0 and 1 (linear in quality), labels."""

    x0: np.ndarray
    x1: np.ndarray
    y: np.ndarray

    @classmethod
    def simulate(cls, seed: int, n: int) -> InformationSession:
        rng = np.random.default_rng([seed, INFORMATION_SESSION])
        y = rng.permutation(np.arange(n) % 2).astype(np.int64)
        x0, x1 = (SubjectRecording(q, seed, INFORMATION_SESSION).epochs(y) for q in (0.0, 1.0))
        return cls(x0, x1, y)

    def at(self, quality: float) -> np.ndarray:
        return (self.x0 + np.float32(quality) * (self.x1 - self.x0)).astype(np.float32)


def trial_variability(
    session: InformationSession, quality: float, channel_index: int
) -> dict[str, float]:
    """The ErrP at ``channel_index``'s negative peak over error trials: mean amplitude, its
    trial-to-trial SD and coefficient of variation (the ErrP alone), the background's SD
    there, and the single-trial SNR (mean^2 / total variance), in microvolts."""
    errors = session.y == 1
    errp = quality * (session.x1 - session.x0)[errors, channel_index] * 1e6
    peak = int(np.argmin(errp.mean(axis=0)))
    amplitude = errp[:, peak]
    background = session.x0[errors, channel_index, peak] * 1e6
    total = amplitude + background
    mean = float(amplitude.mean())
    return {
        "peak_ms": 1000.0 * peak / 128.0,
        "errp_mean_uv": mean,
        "errp_sd_uv": float(amplitude.std()),
        "errp_cv": float(amplitude.std() / abs(mean)) if mean else math.nan,
        "background_sd_uv": float(background.std()),
        "single_trial_snr": float(mean**2 / total.var()),
    }


def channel_information(
    y: np.ndarray, p_error: np.ndarray, calibration: PosteriorCalibration, n_resamples: int
) -> dict[str, Any]:
    """Both channels' bits per label on held-out epochs (``y``: 1 = error, half errors)."""
    decided = (p_error >= 0.5).astype(np.int64)
    llr = calibration.log_likelihood_ratio(p_error)
    threshold = float(calibration.log_likelihood_ratio(np.array([0.5]))[0])
    edges = soft_bin_edges(llr, threshold)
    accuracy = float(np.mean(decided == y))
    soft = soft_information(y, llr, edges)
    soft_ci = bootstrap_interval(
        lambda i: soft_information(y[i], llr[i], edges), y.size, n_resamples=n_resamples
    )
    hard_ci = bootstrap_interval(
        lambda i: plugin_information(y[i], decided[i]), y.size, n_resamples=n_resamples
    )
    reference_hard, reference_soft = gaussian_reference(min(max(accuracy, 0.5001), 0.9999))
    return {
        "n_epochs": int(y.size),
        "accuracy": accuracy,
        "hard_bits_bsc": hard_bits(accuracy),
        "hard_information": plugin_information(y, decided),
        "hard_information_ci": list(hard_ci),
        "soft_information": soft,
        "soft_information_ci": list(soft_ci),
        "soft_over_hard": soft / hard_bits(accuracy) if accuracy > 0.5 else None,
        "gaussian_reference_hard": reference_hard,
        "gaussian_reference_soft": reference_soft,
    }


def measure_subject(
    seed: int,
    targets: list[float],
    config: TrainingConfig,
    *,
    cache_dir: str | None,
    n_epochs: int = INFORMATION_EPOCHS,
    n_resamples: int = 1000,
) -> list[dict[str, Any]]:
    """One row per target accuracy for virtual subject ``seed``."""
    epochs = SubjectEpochs.simulate(seed)
    session = InformationSession.simulate(seed, n_epochs)
    channel = epochs.ch_names.index(VARIABILITY_CHANNEL)
    rows = []
    for target in targets:
        search = find_quality(
            seed, target, config, cache_dir=cache_dir, epochs=epochs, strict=False
        )
        subject = calibrate_subject(epochs, search.facts.quality, config)
        assert subject.classifier.calibration is not None
        X = session.at(search.facts.quality)
        figures = channel_information(
            session.y,
            subject.classifier.predict_proba(X),
            subject.classifier.calibration,
            n_resamples,
        )
        rows.append(
            {
                "seed": seed,
                "target_accuracy": target,
                "subject_quality": search.facts.quality,
                "decoder": search.facts.decoder,
                "search_accuracy": search.facts.decoder_accuracy,
                "target_reached": search.reached,
                **figures,
                "test_ece": search.facts.test_ece,
                "variability": trial_variability(session, search.facts.quality, channel),
            }
        )
    return rows


def summarize(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per target accuracy: means over subjects of the figures the table shows."""
    out = []
    for target in sorted({r["target_accuracy"] for r in rows}):
        group = [r for r in rows if r["target_accuracy"] == target]

        def mean(key: str, rows_: list[dict[str, Any]] = group) -> float:
            return float(np.mean([r[key] for r in rows_]))

        out.append(
            {
                "target_accuracy": target,
                "subjects": len(group),
                "reached": sum(bool(r.get("target_reached", True)) for r in group),
                "accuracy": mean("accuracy"),
                "subject_quality": mean("subject_quality"),
                "hard_bits_bsc": mean("hard_bits_bsc"),
                "hard_information": mean("hard_information"),
                "soft_information": mean("soft_information"),
                "soft_information_ci_low": float(
                    np.mean([r["soft_information_ci"][0] for r in group])
                ),
                "soft_information_ci_high": float(
                    np.mean([r["soft_information_ci"][1] for r in group])
                ),
                "soft_over_hard": float(np.mean([r["soft_information"] for r in group]))
                / max(mean("hard_bits_bsc"), 1e-12),
                "gaussian_reference_ratio": mean("gaussian_reference_soft")
                / max(mean("gaussian_reference_hard"), 1e-12),
                "errp_mean_uv": float(np.mean([r["variability"]["errp_mean_uv"] for r in group])),
                "errp_cv": float(np.mean([r["variability"]["errp_cv"] for r in group])),
                "background_sd_uv": float(
                    np.mean([r["variability"]["background_sd_uv"] for r in group])
                ),
                "single_trial_snr": float(
                    np.mean([r["variability"]["single_trial_snr"] for r in group])
                ),
            }
        )
    return out


def format_table(summary: list[dict[str, Any]]) -> str:
    """The markdown table of :func:`summarize`."""
    lines = [
        "| target acc. | subjects (within 0.02) | held-out acc. | quality | hard: 1 - H(err) "
        "| hard: I(decision; truth) | soft: I(posterior; truth) [95 % CI] | soft / hard "
        "| Gaussian-score soft / hard "
        "| ErrP at FCz (µV) | ErrP trial CV | background SD (µV) | single-trial SNR |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for s in summary:
        lines.append(
            f"| {s['target_accuracy']:.2f} | {s['subjects']} ({s['reached']}) "
            f"| {s['accuracy']:.3f} "
            f"| {s['subject_quality']:.3f} | {s['hard_bits_bsc']:.4f} "
            f"| {s['hard_information']:.4f} "
            f"| {s['soft_information']:.4f} [{s['soft_information_ci_low']:.4f}, "
            f"{s['soft_information_ci_high']:.4f}] | {s['soft_over_hard']:.2f} "
            f"| {s['gaussian_reference_ratio']:.2f} | {s['errp_mean_uv']:.2f} "
            f"| {s['errp_cv']:.2f} | {s['background_sd_uv']:.1f} | {s['single_trial_snr']:.3f} |"
        )
    return "\n".join(lines)
