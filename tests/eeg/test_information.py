"""Bits per label: the hard and the soft channel's estimators against hand numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.eeg.decoding.information import (
    bootstrap_interval,
    gaussian_reference,
    hard_bits,
    plugin_information,
    soft_bin_edges,
    soft_information,
)


def test_hard_bits_and_plugin_information_against_hand_numbers() -> None:
    assert hard_bits(0.6) == pytest.approx(1 + 0.4 * math.log2(0.4) + 0.6 * math.log2(0.6))
    assert hard_bits(0.6) == pytest.approx(0.0290, abs=1e-4)
    assert hard_bits(0.5) == 0.0 and hard_bits(1.0) == 1.0
    # independent cells: plug-in 0, Miller-Madow -(4 - 2 - 2 + 1) / (2 * 8 * ln 2)
    y = np.array([0, 1, 0, 1, 0, 1, 0, 1])
    cells = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    assert plugin_information(y, cells) == pytest.approx(-1 / (16 * math.log(2)))
    # cells equal to the truth: 1 bit, plus (2 + 2 - 2 - 1) / (2 * 8 * ln 2)
    assert plugin_information(y, y) == pytest.approx(1 + 1 / (16 * math.log(2)))


def test_soft_information_of_gaussian_scores_matches_the_reference_and_beats_hard() -> None:
    reference_hard, reference_soft = gaussian_reference(0.6)
    assert reference_hard == pytest.approx(hard_bits(0.6))
    assert 1.45 < reference_soft / reference_hard < 1.6  # near pi / 2 at low SNR
    rng = np.random.default_rng(0)
    n = 40_000
    y = rng.permutation(np.arange(n) % 2)
    d = 2 * 0.2533471  # Phi(d / 2) = 0.6
    score = rng.normal(np.where(y == 1, d / 2, -d / 2), 1.0)
    edges = soft_bin_edges(score, 0.0, n_bins=20)
    assert 0.0 in edges
    soft = soft_information(y, score, edges)
    hard = plugin_information(y, (score >= 0).astype(np.int64))
    assert hard == pytest.approx(reference_hard, abs=0.006)
    assert soft == pytest.approx(reference_soft, abs=0.008)
    assert soft > hard
    low, high = bootstrap_interval(
        lambda i: soft_information(y[i], score[i], edges), n, n_resamples=100
    )
    assert low < soft < high and high - low < 0.03
