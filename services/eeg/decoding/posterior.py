"""Calibrated decoder output: P(error | epoch) and the likelihood ratio stage 2 takes.

A decoder trained with balanced class weights outputs a score, not a probability: its
P(error) is pulled toward 0.5 and ignores the error rate. :func:`fit_platt` fits Platt
scaling (Platt 1999; a logistic regression of the label on the score's logit, with Platt's
smoothed targets) on held-out epochs, the calibration session's validation split:

    P(error | epoch) = sigmoid(slope * logit(p_raw) + intercept).

That posterior holds the calibration session's error rate ``prior_error``; stage 2 wants the
evidence of the epoch alone, the likelihood ratio

    P(epoch | error) / P(epoch | correct) = posterior odds / prior odds

(:meth:`PosteriorCalibration.log_likelihood_ratio`), which it combines with its own belief
about the action (docs/stage2.md, "Soft labels"). :func:`expected_calibration_error` and
:func:`reliability_bins` measure how well a probability is calibrated (equal-width bins of the
predicted P(error); Naeini et al., AAAI 2015; Guo et al., ICML 2017).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import optimize, special

PROBABILITY_FLOOR = 1e-6
"""Decoder outputs are clipped to [floor, 1 - floor] before their logit is taken (an sLDA
can answer exactly 0 or 1)."""
N_BINS = 10
"""Equal-width bins of the reliability diagram and the ECE."""
CALIBRATION_METHOD = "platt"


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(np.asarray(p, dtype=np.float64), PROBABILITY_FLOOR, 1.0 - PROBABILITY_FLOOR)
    return special.logit(p)


@dataclass(frozen=True)
class PosteriorCalibration:
    """Platt scaling of a decoder's P(error), fitted on held-out epochs.

    Attributes
    ----------
    slope, intercept : float
        ``P(error | epoch) = sigmoid(slope * logit(p_raw) + intercept)``.
    prior_error : float
        Error fraction of the epochs it was fitted on (the posterior's base rate).
    n_fit : int
        Epochs it was fitted on.
    method : str
        ``platt``.
    """

    slope: float
    intercept: float
    prior_error: float
    n_fit: int
    method: str = CALIBRATION_METHOD

    def __post_init__(self) -> None:
        if self.method != CALIBRATION_METHOD:
            raise ValueError(f"unknown posterior calibration {self.method!r}")
        if not all(math.isfinite(v) for v in (self.slope, self.intercept)):
            raise ValueError("calibration slope and intercept must be finite")
        if not 0.0 < self.prior_error < 1.0:
            raise ValueError(f"prior_error must be in (0, 1), got {self.prior_error}")

    def posterior_logit(self, p_raw: np.ndarray) -> np.ndarray:
        """logit P(error | epoch) at the calibration session's error rate."""
        return self.slope * _logit(p_raw) + self.intercept

    def posterior(self, p_raw: np.ndarray) -> np.ndarray:
        """Calibrated P(error | epoch), shape of ``p_raw``."""
        return special.expit(self.posterior_logit(p_raw))

    def log_likelihood_ratio(self, p_raw: np.ndarray) -> np.ndarray:
        """``log P(epoch | error) / P(epoch | correct)``: the posterior's log-odds minus the
        prior's, so it holds the epoch's evidence whatever the error rate."""
        prior = math.log(self.prior_error / (1.0 - self.prior_error))
        return self.posterior_logit(p_raw) - prior

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (``classifier.json``'s ``calibration``)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PosteriorCalibration:
        """Rebuild from :meth:`to_dict`; ``ValueError`` for a malformed entry."""
        try:
            return cls(
                slope=float(data["slope"]),
                intercept=float(data["intercept"]),
                prior_error=float(data["prior_error"]),
                n_fit=int(data["n_fit"]),
                method=str(data.get("method", CALIBRATION_METHOD)),
            )
        except (KeyError, TypeError) as exc:
            raise ValueError(f"malformed posterior calibration: {exc}") from None


def fit_platt(y: np.ndarray, p_raw: np.ndarray) -> PosteriorCalibration:
    """Platt scaling of ``p_raw`` (P(error) per epoch) against labels ``y`` (1 = error).

    Minimises the cross-entropy of ``sigmoid(a logit(p_raw) + b)`` against Platt's smoothed
    targets ``(N+ + 1) / (N+ + 2)`` and ``1 / (N- + 2)``, which keep a small held-out set
    (e.g. 72 validation epochs) from driving the fit to certainty.
    """
    y = np.asarray(y).astype(np.int64)
    x = _logit(p_raw)
    if y.shape != x.shape or y.ndim != 1:
        raise ValueError(f"labels {y.shape} and probabilities {x.shape} must be one equal length")
    n_error = int(y.sum())
    n_correct = int(y.size - n_error)
    if n_error == 0 or n_correct == 0:
        raise ValueError("posterior calibration needs both correct and error epochs")
    target = np.where(y == 1, (n_error + 1) / (n_error + 2), 1.0 / (n_correct + 2))

    def loss(params: np.ndarray) -> tuple[float, np.ndarray]:
        z = params[0] * x + params[1]
        # cross-entropy with soft targets: softplus(z) - t z
        value = float(np.sum(np.logaddexp(0.0, z) - target * z))
        residual = special.expit(z) - target
        return value, np.array([np.sum(residual * x), np.sum(residual)])

    fit = optimize.minimize(loss, np.array([1.0, 0.0]), jac=True, method="BFGS")
    slope, intercept = (float(v) for v in fit.x)
    return PosteriorCalibration(slope, intercept, n_error / y.size, int(y.size))


def reliability_bins(y: np.ndarray, p: np.ndarray, n_bins: int = N_BINS) -> list[dict[str, Any]]:
    """The reliability diagram's points: per equal-width bin of P(error) that holds epochs,
    its range, the epochs in it, their mean P(error) and their fraction of errors."""
    y = np.asarray(y, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    index = np.minimum((p * n_bins).astype(np.int64), n_bins - 1)
    rows = []
    for b in range(n_bins):
        inside = index == b
        if inside.any():
            rows.append(
                {
                    "low": b / n_bins,
                    "high": (b + 1) / n_bins,
                    "count": int(inside.sum()),
                    "mean_p_error": float(p[inside].mean()),
                    "error_fraction": float(y[inside].mean()),
                }
            )
    return rows


def expected_calibration_error(y: np.ndarray, p: np.ndarray, n_bins: int = N_BINS) -> float:
    """ECE: the epoch-weighted mean of |error fraction - mean P(error)| over the bins."""
    rows = reliability_bins(y, p, n_bins)
    total = sum(r["count"] for r in rows)
    if total == 0:
        return float("nan")
    return float(
        sum(r["count"] * abs(r["error_fraction"] - r["mean_p_error"]) for r in rows) / total
    )


def calibration_report(
    calibration: PosteriorCalibration, y_test: np.ndarray, p_test_raw: np.ndarray
) -> dict[str, Any]:
    """``metrics.json``'s ``calibration``: the fit and, on the test epochs, the ECE and the
    reliability bins of the raw and the calibrated P(error)."""
    calibrated = calibration.posterior(p_test_raw)
    return {
        **calibration.to_dict(),
        "fitted_on": "validation",
        "n_bins": N_BINS,
        "test_ece_raw": expected_calibration_error(y_test, p_test_raw),
        "test_ece": expected_calibration_error(y_test, calibrated),
        "test_reliability_raw": reliability_bins(y_test, p_test_raw),
        "test_reliability": reliability_bins(y_test, calibrated),
    }
