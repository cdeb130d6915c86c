"""The registered tests of docs/protocol.md on small hand-checked cases."""

from __future__ import annotations

import dataclasses
import math

import pytest

from services.learner.confirmatory import (
    CONFIRMATORY_SEEDS,
    H6_FAMILY,
    H6_SEEDS,
    analyse,
    analyse_h6,
    binomial_greater,
    censored_steps,
    exact_mcnemar,
    markdown_table,
    plot_estimates,
    wilcoxon_above,
    wilcoxon_fewer_steps,
)
from services.learner.runs import RunRecord, steps_to_reach


def _run(method: str, seed: int, reach_at: int | None, task: str = "sssg", **extra) -> RunRecord:
    curve = [[2000 * k, 1.0 if reach_at is not None and 2000 * k >= reach_at else 0.0]
             for k in range(21)]  # fmt: skip
    return RunRecord(
        task=task, method=method, accuracy=None, seed=seed, hf_treatment=None, curve=curve,
        final_spl=curve[-1][1], hf_policy_spl=extra.pop("hf_spl", None), wall_seconds=1.0,
        steps_to_0_7=steps_to_reach(curve), **extra,
    )  # fmt: skip


def test_the_tests_against_hand_numbers() -> None:
    assert censored_steps(_run("rl_sparse", 0, None)) == 42_000  # 40 000 + one evaluation
    assert censored_steps(_run("rl_sparse", 0, 6000)) == 6000
    # discordant: 2 first only, 1 second only -> P(X >= 2 | 3, 1/2) = 4/8
    assert exact_mcnemar([True, True, True, False], [False, False, True, True]) == (2, 1, 0.5)
    assert exact_mcnemar([True, False], [True, False])[2] == 1.0
    assert binomial_greater(16, 20) == pytest.approx((4845 + 1140 + 190 + 20 + 1) / 2**20)
    # 8 pairs all in favour: exact p = 1/2^8; all equal: nothing to rank
    assert wilcoxon_fewer_steps(range(8), [10 + k for k in range(8)]) == pytest.approx(1 / 256)
    assert wilcoxon_fewer_steps([42_000] * 5, [42_000] * 5) == 1.0
    assert wilcoxon_above([1.6, 1.7, 1.8, 1.9], 1.5) == pytest.approx(1 / 16)
    assert wilcoxon_above([1.4, 1.3, 1.2, 1.1], 1.5) == pytest.approx(1.0)


def _information_row(seed: int, ratio: float) -> dict:
    return {"seed": seed, "target_accuracy": 0.6, "accuracy": 0.6, "target_reached": True,
            "soft_information": 0.029 * ratio, "hard_bits_bsc": 0.029}  # fmt: skip


def test_analysis_of_a_family_with_data_for_two_hypotheses(tmp_path) -> None:
    seeds = CONFIRMATORY_SEEDS
    # HF reaches 0.7 at 2000, 4000, ..., 40 000 (distinct differences: the exact test)
    e2e = [_run("hf_sparse", s, 2000 * (i + 1), hf_spl=0.6 if i % 2 else 0.4,
                feedback="virtual_subject", decoder_accuracy=0.61 if i else 0.55)
           for i, s in enumerate(seeds)]  # fmt: skip
    e2e += [_run("rl_sparse", s, None) for s in seeds]
    e2e += [_run("hf_sparse", 5, None), _run("rl_sparse", 5, 2000)]  # a tuning seed: left out
    information = [_information_row(s, 1.4 + 0.001 * i) for i, s in enumerate(seeds)]
    results = analyse(e2e, None, None, None, information)
    by_name = {r.hypothesis: r for r in results}
    h1a, h5 = by_name["H1a"], by_name["H5"]
    assert h1a.n == 20 and h1a.p_raw == pytest.approx(0.5**20)
    assert h1a.threshold_met is True  # 20/20 reach; last five: (16 + 0.8 + ... + 0.2) / 20
    assert h1a.estimates[3].label == "HF last-5 SPL" and h1a.estimates[3].value == pytest.approx(
        0.9
    )
    assert [e.k for e in h1a.estimates if e.kind == "count"] == [20, 0, 10]
    assert "outside 0.60 +- 0.02 (kept): 1000: 0.550" in h1a.detail
    assert by_name["H1b"].missing is not None and by_name["H1b"].verdict == "not run"
    assert h5.threshold_met is False and h5.p_raw == pytest.approx(1.0)
    # Holm over the two with data (a lower bound), 9 p over the family (an upper one)
    assert h1a.p_holm == pytest.approx(2 * h1a.p_raw)
    assert h1a.p_family_bound == pytest.approx(9 * h1a.p_raw)
    assert h1a.verdict == "confirmed"
    assert h5.p_holm == pytest.approx(1.0) and h5.verdict == "not confirmed"
    table = markdown_table(results)
    assert "Not run: H1b, H2a, H2b, H3a, H3b, H4a, H4b" in table
    assert plot_estimates(results, "count", tmp_path / "c.png") == tmp_path / "c.png"
    assert (tmp_path / "c.png").stat().st_size > 0
    assert plot_estimates(analyse(None, None, None, None, None), "mean", tmp_path / "m.png") is None


def test_a_partial_hypothesis_is_reported_but_not_decided() -> None:
    seeds = CONFIRMATORY_SEEDS[:7]
    on = [_run("hf_sparse", s, 4000) for s in seeds]
    off = [_run("hf_sparse", s, None if s < 1005 else 4000) for s in seeds]
    (h2a,) = [r for r in analyse(None, on, off, None, None) if r.hypothesis == "H2a"]
    assert h2a.n == 7 and h2a.p_raw == pytest.approx(1 / 32)  # 5 discordant, all with SIL
    assert h2a.p_holm is None and h2a.verdict.startswith("partial (7/20")
    assert math.isclose(h2a.estimates[0].value, 1.0)


def test_a_hypothesis_the_missing_ones_can_still_overturn_is_provisional() -> None:
    """Raw p 1/64 (6 discordant pairs): Holm over itself 0.016 < 0.05, 9 p = 0.14."""
    seeds = CONFIRMATORY_SEEDS
    on = [_run("hf_sparse", s, 4000) for s in seeds]
    off = [_run("hf_sparse", s, None if s < 1006 else 4000) for s in seeds]
    (h2a,) = [r for r in analyse(None, on, off, None, None) if r.hypothesis == "H2a"]
    assert h2a.p_raw == pytest.approx(1 / 64) and h2a.p_holm == pytest.approx(1 / 64)
    assert h2a.p_family_bound == pytest.approx(9 / 64)
    assert h2a.verdict.startswith("provisionally confirmed")


def _tail_run(method: str, seed: int, last_five: float, reach_at: int | None = 2000) -> RunRecord:
    """A run reaching 1.0 at ``reach_at`` whose last five evaluations are ``last_five``."""
    run = _run(method, seed, reach_at)
    curve = [*run.curve[:-5], *([step, last_five] for step, _ in run.curve[-5:])]
    return dataclasses.replace(run, curve=curve)


def test_the_second_family_h6_on_its_own_seeds_with_holm_over_four(tmp_path) -> None:
    seeds = H6_SEEDS
    # annealed HF last five 0.9 on every seed; constant 0.5 + 0.01 i: 20 positive differences
    annealed = [_tail_run("hf_sparse", s, 0.9, 2000 * (i + 1)) for i, s in enumerate(seeds)]
    annealed += [_tail_run("rl_sparse", s, 0.0, reach_at=None) for s in seeds]
    constant = [_tail_run("hf_sparse", s, 0.5 + 0.01 * i) for i, s in enumerate(seeds)]
    # a first-family seed and a tuning seed in the same files: both left out
    annealed += [_tail_run("hf_sparse", 1000, 0.0), _tail_run("rl_sparse", 1000, 1.0, 2000)]
    constant += [_tail_run("hf_sparse", 100, 1.0)]
    results = analyse_h6(annealed, constant)
    by_name = {r.hypothesis: r for r in results}
    assert list(by_name) == list(H6_FAMILY)
    last5, accel = by_name["H6a-last5"], by_name["H6a-accel"]
    assert last5.n == 20 and last5.p_raw == pytest.approx(0.5**20)
    assert last5.threshold_met is True and "higher with annealing on 20" in last5.detail
    assert [e.value for e in last5.estimates] == pytest.approx([0.9, 0.595, 0.305])
    # annealed HF reaches at 2000, 4000, ..., 40 000, annealed RL never: H1's exact test
    assert accel.n == 20 and accel.p_raw == pytest.approx(0.5**20)
    assert accel.threshold_met is True  # 20/20 reach; no last-five condition
    # Holm over the two complete ones with data; the bound is over the family of four
    assert last5.p_holm == pytest.approx(2 * 0.5**20)
    assert last5.p_family_bound == pytest.approx(4 * 0.5**20)
    assert last5.verdict == accel.verdict == "confirmed"
    assert by_name["H6b-last5"].verdict == "not run"
    table = markdown_table(results)
    assert "bound over 4 (4 p)" in table and "Not run: H6b-last5, H6b-accel" in table
    assert plot_estimates(results, "mean", tmp_path / "m.png") == tmp_path / "m.png"


def test_h6_last5_below_its_threshold_and_without_a_difference() -> None:
    seeds = H6_SEEDS
    same = [_tail_run("hf_sparse", s, 0.7) for s in seeds]
    by_name = {r.hypothesis: r for r in analyse_h6(same, same)}
    assert by_name["H6b-last5"].missing is not None  # SSSG runs only: VSSG not run
    last5a = by_name["H6a-last5"]
    assert last5a.p_raw == 1.0 and last5a.threshold_met is False  # every pair equal; 0.7 < 0.8
    assert last5a.verdict == "not confirmed"
