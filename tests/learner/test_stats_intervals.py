"""Wilson intervals, bootstrap intervals of means and Holm's correction (docs/protocol.md)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest

from services.learner.stats import bootstrap_mean_interval, holm_adjust, wilson_interval


@pytest.mark.parametrize(("k", "n"), [(17, 20), (0, 20), (20, 20), (3, 10)])
def test_wilson_interval_equals_scipys(k: int, n: int) -> None:
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_wilson_interval_hand_value_and_bad_input() -> None:
    assert wilson_interval(17, 20) == pytest.approx((0.6396, 0.9476), abs=1e-4)
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def test_holm_adjusted_p_values_are_the_hand_values() -> None:
    """Sorted 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1, made monotone: 0.02, 0.03, 0.06, 0.06."""
    assert holm_adjust([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjust([0.5, 0.9]) == pytest.approx([1.0, 1.0])


def test_bootstrap_interval_covers_the_mean_and_narrows_with_more_runs() -> None:
    rng = np.random.default_rng(0)
    small = rng.random(10)
    large = rng.random(400)
    lo, hi = bootstrap_mean_interval(small)
    assert lo < small.mean() < hi
    lo_l, hi_l = bootstrap_mean_interval(large)
    assert lo_l < 0.5 < hi_l and hi_l - lo_l < hi - lo
    assert bootstrap_mean_interval([0.7, 0.7, 0.7]) == (0.7, 0.7)
    assert bootstrap_mean_interval(small) == (lo, hi)  # reproducible
