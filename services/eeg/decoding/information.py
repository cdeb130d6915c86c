"""Information per label, in bits: what a decoded epoch tells about "was the action an error".

With the truth a fair coin (half errors, the channel's capacity for a symmetric channel):

* **hard channel**: the thresholded decision. ``hard_bits(accuracy) = 1 - H(1 - accuracy)``
  is a binary symmetric channel's capacity; :func:`plugin_information` on the decisions
  measures the asymmetric channel a decoder really is.
* **soft channel**: the calibrated posterior (equivalently its log-likelihood ratio, a
  monotone map of the decoder's P(error)). :func:`soft_information` bins it (quantile bins of
  the held-out set, with the hard threshold as one more edge, so the binned variable refines
  the hard decision and, by the data-processing inequality, its estimate is not below the
  hard one's) and takes the plug-in mutual information with the Miller-Madow bias correction
  (Paninski, Neural Computation 2003); :func:`bootstrap_interval` resamples epochs.
* :func:`gaussian_reference`: both channels for equal-variance Gaussian scores at the same
  accuracy; at low signal-to-noise the soft channel carries pi/2 times the hard one's bits
  (the classical loss of hard decisions).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import integrate, stats

N_SOFT_BINS = 10


def binary_entropy(p: float) -> float:
    """H(p) in bits (0 at 0 and 1)."""
    if p <= 0.0 or p >= 1.0:
        return 0.0
    return float(-(p * math.log2(p) + (1 - p) * math.log2(1 - p)))


def hard_bits(accuracy: float) -> float:
    """``1 - H(1 - accuracy)``: bits per label of a binary symmetric channel."""
    return 1.0 - binary_entropy(1.0 - accuracy)


def plugin_information(y: np.ndarray, cells: np.ndarray) -> float:
    """I(Y; cell) in bits, plug-in with the Miller-Madow correction, for integer ``cells``."""
    y = np.asarray(y, dtype=np.int64)
    cells = np.asarray(cells, dtype=np.int64)
    n = y.size
    joint = np.zeros((int(cells.max()) + 1, 2))
    np.add.at(joint, (cells, y), 1.0)
    joint = joint[joint.sum(axis=1) > 0]
    p_joint = joint / n
    p_cell = p_joint.sum(axis=1, keepdims=True)
    p_y = p_joint.sum(axis=0, keepdims=True)
    inside = p_joint > 0
    plugin = float(np.sum(p_joint[inside] * np.log2(p_joint[inside] / (p_cell @ p_y)[inside])))
    n_joint, n_cell, n_y = int(inside.sum()), int(joint.shape[0]), int((p_y > 0).sum())
    return plugin - (n_joint - n_cell - n_y + 1) / (2.0 * n * math.log(2.0))


def soft_bin_edges(score: np.ndarray, threshold: float, n_bins: int = N_SOFT_BINS) -> np.ndarray:
    """Inner edges: the score's quantiles and the hard decision's threshold."""
    quantiles = np.quantile(score, np.linspace(0, 1, n_bins + 1)[1:-1])
    return np.unique(np.append(quantiles, threshold))


def soft_information(y: np.ndarray, score: np.ndarray, edges: np.ndarray) -> float:
    """I(Y; binned score) in bits (Miller-Madow corrected)."""
    return plugin_information(y, np.searchsorted(edges, score, side="right"))


def bootstrap_interval(
    statistic: Callable[[np.ndarray], float],
    n: int,
    *,
    n_resamples: int = 1000,
    seed: int = 0,
    level: float = 0.95,
) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic(indices)`` over ``n`` items."""
    rng = np.random.default_rng(seed)
    values = [statistic(rng.integers(0, n, n)) for _ in range(n_resamples)]
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(values, [tail, 100 - tail])
    return float(low), float(high)


def gaussian_reference(accuracy: float) -> tuple[float, float]:
    """(hard, soft) bits per label for Gaussian scores N(+-d/2, 1) at equal priors whose
    thresholded accuracy is ``accuracy`` (d = 2 Phi^-1(accuracy))."""
    d = 2.0 * stats.norm.ppf(accuracy)

    def integrand(x: float) -> float:
        error = stats.norm.pdf(x, d / 2)
        correct = stats.norm.pdf(x, -d / 2)
        posterior = error / (error + correct)
        return 0.5 * (error + correct) * binary_entropy(posterior)

    conditional, _ = integrate.quad(integrand, -d / 2 - 12, d / 2 + 12, limit=200)
    return hard_bits(accuracy), 1.0 - conditional
