"""The confirmatory analyses of docs/protocol.md: its two registered families.

Every hypothesis is computed from stored rows only. First family (:func:`analyse`, seeds
1000-1019): ``results.json`` runs of ``bgrl reproduce`` (H1: end to end; H2: self-imitation
on/off), ``nstar_rows.json`` of ``bgrl hf-nstar`` (H3, H4) and ``information.json`` of
``bgrl eeg information`` (H5). Second family (:func:`analyse_h6`, seeds 4000-4019): the end
to end runs with and without ``anneal_lr`` (H6). Only a family's own seeds enter; a tuning
seed is never pooled with them.

Tests, as registered: one-sided Wilcoxon signed-rank on the paired steps to SPL 0.7 with
censoring (H1), one-sided exact McNemar on paired outcomes (H2, H4), one-sided exact binomial
against 1/2 (H3), one-sided Wilcoxon signed-rank of ``ratio - 1.5`` (H5), one-sided
Wilcoxon signed-rank of the paired last-five differences (H6 last-five; H6 acceleration is
H1's test). Holm's step-down adjustment (:func:`~services.learner.stats.holm_adjust`) runs
within a family over its complete hypotheses, a lower bound of the family's Holm p; the
family's size times p bounds it from above. Counts carry Wilson 95 % intervals, means
bootstrap 95 % intervals.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.learner.ppo import PPOConfig
from services.learner.runs import RunRecord
from services.learner.specs import DECODER_ACCURACY_TOLERANCE
from services.learner.stage2_report import USEFUL_SPL
from services.learner.stats import (
    LAST_EVALS,
    bootstrap_mean_interval,
    holm_adjust,
    wilson_interval,
)

CONFIRMATORY_SEEDS = tuple(range(1000, 1020))
"""docs/protocol.md: 20 fresh seeds per task (and 20 fresh virtual subjects for H5)."""
ALPHA = 0.05
TASKS = ("sssg", "vssg")
FAMILY = ("H1a", "H1b", "H2a", "H2b", "H3a", "H3b", "H4a", "H4b", "H5")
"""The registered family (a: SSSG, b: VSSG)."""
H1_REACH_SHARE = 17 / 20
H1_LAST5_MIN = 0.8
USEFUL_SHARE = 16 / 20
"""H3, H4: >= 16/20 useful pi_HF (the N* criterion)."""
H5_RATIO = 1.5
H3_LABELS, H4_LABELS = 4000, 2000
ORACLE_C = 0.6
H1_DECODER_TARGET = 0.6
H5_TARGET = 0.6
H6_SEEDS = tuple(range(4000, 4020))
"""docs/protocol.md, second family: fresh seeds and virtual subjects 4000-4019 per task."""
H6_FAMILY = ("H6a-last5", "H6a-accel", "H6b-last5", "H6b-accel")
H6_LAST5_MIN = 0.8
_ACCELERATION_TEST = "one-sided Wilcoxon signed-rank, paired steps to 0.7 (censored at 42 000)"


@dataclass(frozen=True)
class Estimate:
    """A count (Wilson interval on the share) or a mean (bootstrap interval) of a hypothesis."""

    label: str
    kind: str
    """``count`` or ``mean``."""
    value: float
    """The share k/n for a count, the mean for a mean."""
    low: float
    high: float
    n: int
    k: int | None = None
    unit: str = "SPL"
    """What a mean measures (``SPL``, ``ratio``, ``bits``): the means figure has one panel
    per unit."""

    def text(self) -> str:
        if self.kind == "count":
            return f"{self.label} {self.k}/{self.n} [{self.low:.2f}, {self.high:.2f}]"
        return f"{self.label} {self.value:#.3g} [{self.low:#.3g}, {self.high:#.3g}]"


def count_estimate(label: str, k: int, n: int) -> Estimate:
    """``k`` of ``n`` runs with the Wilson 95 % interval of the share."""
    low, high = wilson_interval(k, n)
    return Estimate(label, "count", k / n, low, high, n, k=k)


def mean_estimate(label: str, values: Sequence[float], unit: str = "SPL") -> Estimate:
    """The mean of ``values`` with its bootstrap 95 % interval (10 000 resamples, seed 0)."""
    low, high = bootstrap_mean_interval(values)
    return Estimate(label, "mean", float(np.mean(values)), low, high, len(values), unit=unit)


@dataclass
class HypothesisResult:
    """One registered hypothesis: its test's raw and Holm-adjusted p, the threshold, the
    estimates, or why it has no data."""

    hypothesis: str
    task: str | None
    claim: str
    test: str
    threshold: str
    n: int = 0
    p_raw: float | None = None
    threshold_met: bool | None = None
    estimates: list[Estimate] = field(default_factory=list)
    missing: str | None = None
    """Why the hypothesis has no data (its runs not made), or None."""
    p_holm: float | None = None
    """Holm over the complete hypotheses with data: a lower bound of the family's Holm p (a
    hypothesis added to a Holm family never lowers another's adjusted p)."""
    p_family_bound: float | None = None
    """Bonferroni over the registered family, min(1, family_size p): an upper bound of the
    family's Holm p whatever the hypotheses not yet run give."""
    detail: str = ""
    seeds: tuple[int, ...] = CONFIRMATORY_SEEDS
    """The family's registered seeds: the hypothesis is complete with all of them."""
    family_size: int = len(FAMILY)

    @property
    def complete(self) -> bool:
        return self.missing is None and self.n == len(self.seeds)

    @property
    def verdict(self) -> str:
        """``confirmed`` / ``not confirmed`` when the bounds of the family's Holm p decide
        it, else ``provisionally confirmed`` (decided once the family is complete)."""
        if self.missing is not None:
            return "not run"
        if not self.complete:
            return f"partial ({self.n}/{len(self.seeds)} seeds): not decided"
        assert self.p_holm is not None and self.p_family_bound is not None
        if not self.threshold_met or self.p_holm >= ALPHA:
            return "not confirmed"
        if self.p_family_bound < ALPHA:
            return "confirmed"
        return (
            f"provisionally confirmed (decided once the family of {self.family_size} is complete)"
        )


def censored_steps(run: RunRecord, config: PPOConfig | None = None) -> int:
    """``steps_to_0_7``, or for a run that never reached 0.7 the budget plus one evaluation
    interval (docs/protocol.md: it ranks after every run that does)."""
    config = config or PPOConfig()
    if run.steps_to_0_7 is not None:
        return run.steps_to_0_7
    return config.total_steps + config.eval_every


def last_five(run: RunRecord) -> float:
    """Mean SPL of the run's last five evaluations (32k-40k steps)."""
    return float(np.mean([spl for _, spl in run.curve[-LAST_EVALS:]]))


def wilcoxon_fewer_steps(hf_steps: Sequence[float], rl_steps: Sequence[float]) -> float:
    """One-sided Wilcoxon signed-rank p that the first needs fewer steps (pairs with equal
    values dropped, ``zero_method="wilcox"``); 1.0 when every pair is equal."""
    from scipy.stats import wilcoxon

    hf, rl = np.asarray(hf_steps, float), np.asarray(rl_steps, float)
    if hf.shape != rl.shape:
        raise ValueError("paired samples of different lengths")
    if np.all(hf == rl):
        return 1.0
    return float(wilcoxon(hf, rl, zero_method="wilcox", alternative="less").pvalue)


def exact_mcnemar(first: Sequence[bool], second: Sequence[bool]) -> tuple[int, int, float]:
    """One-sided exact McNemar test that ``first`` succeeds more often than ``second`` on
    the same seeds: (b = first only, c = second only, binomtest(b, b + c, 1/2,
    "greater") p); p = 1.0 without discordant pairs."""
    from scipy.stats import binomtest

    if len(first) != len(second):
        raise ValueError("paired outcomes of different lengths")
    b = sum(bool(x) and not bool(y) for x, y in zip(first, second, strict=True))
    c = sum(bool(y) and not bool(x) for x, y in zip(first, second, strict=True))
    if b + c == 0:
        return b, c, 1.0
    return b, c, float(binomtest(b, b + c, 0.5, alternative="greater").pvalue)


def binomial_greater(k: int, n: int) -> float:
    """One-sided exact binomial p of ``k`` successes in ``n`` against 1/2."""
    from scipy.stats import binomtest

    return float(binomtest(k, n, 0.5, alternative="greater").pvalue)


def wilcoxon_above(values: Sequence[float], bound: float) -> float:
    """One-sided Wilcoxon signed-rank p that ``values - bound`` is > 0 (values equal to
    ``bound`` dropped, ``zero_method="wilcox"``); 1.0 when every value equals it."""
    from scipy.stats import wilcoxon

    differences = np.asarray(values, float) - bound
    if np.all(differences == 0):
        return 1.0
    return float(wilcoxon(differences, zero_method="wilcox", alternative="greater").pvalue)


def _confirmatory(
    runs: Sequence[RunRecord], task: str, method: str, seeds: Sequence[int] = CONFIRMATORY_SEEDS
) -> dict[int, RunRecord]:
    return {r.seed: r for r in runs if r.task == task and r.method == method and r.seed in seeds}


def _suffix(task: str) -> str:
    return "a" if task == "sssg" else "b"


def h1(task: str, runs: Sequence[RunRecord] | None) -> HypothesisResult:
    """End-to-end feedback at decoder accuracy 0.6 accelerates learning (same-run RL-sparse)."""
    result = HypothesisResult(
        f"H1{_suffix(task)}",
        task,
        "HF+sparse (virtual subject, decoder 0.6, soft) reaches SPL 0.7 in fewer steps "
        "than RL-sparse",
        _ACCELERATION_TEST,
        ">= 17/20 HF runs reach 0.7 and their last-five mean >= 0.8",
    )
    return _acceleration(result, runs, last_five_min=H1_LAST5_MIN)


def _acceleration(
    result: HypothesisResult, runs: Sequence[RunRecord] | None, last_five_min: float | None
) -> HypothesisResult:
    """H1's test on ``runs`` of ``result``'s task and seeds: HF+sparse against RL-sparse on
    the paired censored steps to 0.7; the threshold is >= 17/20 HF runs reaching 0.7 and,
    unless ``last_five_min`` is None, their last-five mean at least that."""
    task = result.task or ""
    hf_runs = _confirmatory(runs or [], task, "hf_sparse", result.seeds)
    rl_runs = _confirmatory(runs or [], task, "rl_sparse", result.seeds)
    seeds = sorted(set(hf_runs) & set(rl_runs))
    if not seeds:
        result.missing = "the end-to-end runs (bgrl reproduce --feedback virtual_subject)"
        return result
    hf = [hf_runs[s] for s in seeds]
    rl = [rl_runs[s] for s in seeds]
    result.n = len(seeds)
    result.p_raw = wilcoxon_fewer_steps(
        [censored_steps(r) for r in hf], [censored_steps(r) for r in rl]
    )
    reach_hf = sum(r.steps_to_0_7 is not None for r in hf)
    reach_rl = sum(r.steps_to_0_7 is not None for r in rl)
    useful = sum((r.hf_policy_spl or 0.0) >= USEFUL_SPL for r in hf)
    tails = [last_five(r) for r in hf]
    result.estimates = [
        count_estimate("HF reach 0.7", reach_hf, len(seeds)),
        count_estimate("RL reach 0.7", reach_rl, len(seeds)),
        count_estimate("useful pi_HF (secondary)", useful, len(seeds)),
        *_means("HF last-5 SPL", tails),
        *_means("RL last-5 SPL", [last_five(r) for r in rl]),
        *_means("pi_HF SPL", [r.hf_policy_spl or 0.0 for r in hf]),
    ]
    result.threshold_met = reach_hf >= H1_REACH_SHARE * len(seeds) - 1e-9 and (
        last_five_min is None or float(np.mean(tails)) >= last_five_min
    )
    decoded = [r.decoder_accuracy for r in hf if r.decoder_accuracy is not None]
    if decoded:
        missed = [
            f"{r.seed}: {r.decoder_accuracy:.3f}"
            for r in hf
            if r.decoder_accuracy is not None
            and abs(r.decoder_accuracy - H1_DECODER_TARGET) > DECODER_ACCURACY_TOLERANCE + 1e-12
        ]
        result.detail = f"decoder accuracy {np.mean(decoded):.3f} on average" + (
            f"; outside 0.60 +- 0.02 (kept): {', '.join(missed)}" if missed else ""
        )
    return result


def h2(
    task: str, with_sil: Sequence[RunRecord] | None, without_sil: Sequence[RunRecord] | None
) -> HypothesisResult:
    """Self-imitation's gain: more seeds reach 0.7 with it than without (oracle C = 0.6)."""
    result = HypothesisResult(
        f"H2{_suffix(task)}",
        task,
        "self-imitation makes more HF+sparse runs reach SPL 0.7 (oracle C = 0.6, 1000 labels)",
        "one-sided exact McNemar, paired reach 0.7",
        "more runs reach 0.7 with self-imitation than without",
    )
    on = _confirmatory(with_sil or [], task, "hf_sparse")
    off = _confirmatory(without_sil or [], task, "hf_sparse")
    seeds = sorted(set(on) & set(off))
    if not seeds:
        result.missing = "the self-imitation runs (sil_on / sil_off)"
        return result
    reach_on = [on[s].steps_to_0_7 is not None for s in seeds]
    reach_off = [off[s].steps_to_0_7 is not None for s in seeds]
    b, c, result.p_raw = exact_mcnemar(reach_on, reach_off)
    result.n = len(seeds)
    result.threshold_met = sum(reach_on) > sum(reach_off)
    result.detail = f"discordant pairs: {b} with SIL only, {c} without SIL only"
    result.estimates = [
        count_estimate("SIL on reach 0.7", sum(reach_on), len(seeds)),
        count_estimate("SIL off reach 0.7", sum(reach_off), len(seeds)),
        *_means("SIL on last-5 SPL", [last_five(on[s]) for s in seeds]),
        *_means("SIL off last-5 SPL", [last_five(off[s]) for s in seeds]),
    ]
    return result


def _nstar_useful(
    rows: Sequence[dict[str, Any]], task: str, method: str, n_labels: int
) -> dict[int, float]:
    """Seed -> greedy SPL of pi_HF at ``n_labels`` (oracle C = 0.6, confirmatory seeds)."""
    return {
        int(r["seed"]): float(r["greedy_spl"])
        for r in rows
        if r.get("feedback", "oracle") == "oracle"
        and r["task"] == task
        and r["method"] == method
        and int(r["n_labels"]) == n_labels
        and math.isclose(float(r["accuracy"]), ORACLE_C)
        and int(r["seed"]) in CONFIRMATORY_SEEDS
    }


def h3(task: str, rows: Sequence[dict[str, Any]] | None) -> HypothesisResult:
    """4000 hard labels at C = 0.6 make pi_HF useful in >= 80 % of seeds."""
    result = HypothesisResult(
        f"H3{_suffix(task)}",
        task,
        "4000 labels at C = 0.6 give a useful pi_HF (categorical_kernel)",
        "one-sided exact binomial against 1/2",
        ">= 16/20 useful (greedy SPL >= 0.5)",
    )
    spl = _nstar_useful(rows or [], task, "categorical_kernel", H3_LABELS)
    if not spl:
        result.missing = "the stage-2 N* runs (bgrl hf-nstar)"
        return result
    useful = sum(v >= USEFUL_SPL for v in spl.values())
    result.n = len(spl)
    result.p_raw = binomial_greater(useful, len(spl))
    result.threshold_met = useful >= USEFUL_SHARE * len(spl) - 1e-9
    result.estimates = [
        count_estimate("useful at 4000", useful, len(spl)),
        *_means("pi_HF SPL at 4000", list(spl.values())),
    ]
    return result


def h4(task: str, rows: Sequence[dict[str, Any]] | None) -> HypothesisResult:
    """bayes_query makes pi_HF useful at 2000 labels more often than categorical_kernel."""
    result = HypothesisResult(
        f"H4{_suffix(task)}",
        task,
        "N*(0.6) halved: bayes_query useful at 2000 labels",
        "one-sided exact McNemar, bayes_query vs categorical_kernel, paired useful",
        ">= 16/20 useful with bayes_query",
    )
    query = _nstar_useful(rows or [], task, "bayes_query", H4_LABELS)
    kernel = _nstar_useful(rows or [], task, "categorical_kernel", H4_LABELS)
    seeds = sorted(set(query) & set(kernel))
    if not seeds:
        result.missing = "the stage-2 N* runs (bgrl hf-nstar)"
        return result
    useful_q = [query[s] >= USEFUL_SPL for s in seeds]
    useful_k = [kernel[s] >= USEFUL_SPL for s in seeds]
    b, c, result.p_raw = exact_mcnemar(useful_q, useful_k)
    result.n = len(seeds)
    result.threshold_met = sum(useful_q) >= USEFUL_SHARE * len(seeds) - 1e-9
    result.detail = f"discordant pairs: {b} bayes_query only, {c} categorical_kernel only"
    result.estimates = [
        count_estimate("bayes_query useful at 2000", sum(useful_q), len(seeds)),
        count_estimate("categorical_kernel useful at 2000", sum(useful_k), len(seeds)),
        *_means("bayes_query pi_HF SPL", [query[s] for s in seeds]),
        *_means("categorical_kernel pi_HF SPL", [kernel[s] for s in seeds]),
    ]
    return result


def h5(rows: Sequence[dict[str, Any]] | None) -> HypothesisResult:
    """The soft channel carries >= 1.5x the hard label's bits at decoder accuracy 0.6."""
    result = HypothesisResult(
        "H5",
        None,
        "soft channel's bits per label >= 1.5x the hard label's at decoder accuracy 0.6",
        "one-sided Wilcoxon signed-rank of ratio - 1.5",
        "median ratio >= 1.5",
    )
    subjects = [
        r
        for r in rows or []
        if math.isclose(float(r["target_accuracy"]), H5_TARGET)
        and int(r["seed"]) in CONFIRMATORY_SEEDS
    ]
    if not subjects:
        result.missing = "the information runs (bgrl eeg information)"
        return result
    ratios = [float(r["soft_information"]) / float(r["hard_bits_bsc"]) for r in subjects]
    result.n = len(subjects)
    result.p_raw = wilcoxon_above(ratios, H5_RATIO)
    median = float(np.median(ratios))
    result.threshold_met = median >= H5_RATIO
    reached = sum(bool(r.get("target_reached", True)) for r in subjects)
    result.detail = (
        f"median ratio {median:.2f}, min {min(ratios):.2f}, max {max(ratios):.2f}; "
        f"held-out accuracy {np.mean([r['accuracy'] for r in subjects]):.3f} on average, "
        f"{reached}/{len(subjects)} subjects within 0.02 of 0.6"
    )
    result.estimates = [
        *_means("soft / hard ratio", ratios, unit="ratio"),
        *_means("soft bits", [float(r["soft_information"]) for r in subjects], unit="bits"),
        *_means("hard bits", [float(r["hard_bits_bsc"]) for r in subjects], unit="bits"),
    ]
    return result


def h6_last5(
    task: str, annealed: Sequence[RunRecord] | None, constant: Sequence[RunRecord] | None
) -> HypothesisResult:
    """Annealing stage 3's learning rate raises HF+sparse's last-five SPL (end to end)."""
    result = HypothesisResult(
        f"H6{_suffix(task)}-last5",
        task,
        "anneal_lr raises HF+sparse's last-five SPL (virtual subject, decoder 0.6, soft)",
        "one-sided Wilcoxon signed-rank, paired last-five SPL, annealed - constant",
        f">= {H6_LAST5_MIN} annealed HF last-five mean",
        seeds=H6_SEEDS,
        family_size=len(H6_FAMILY),
    )
    on = _confirmatory(annealed or [], task, "hf_sparse", H6_SEEDS)
    off = _confirmatory(constant or [], task, "hf_sparse", H6_SEEDS)
    seeds = sorted(set(on) & set(off))
    if not seeds:
        result.missing = "the H6 runs with and without anneal_lr (confirm6/anneal, base)"
        return result
    tails_on = [last_five(on[s]) for s in seeds]
    tails_off = [last_five(off[s]) for s in seeds]
    differences = [a - b for a, b in zip(tails_on, tails_off, strict=True)]
    result.n = len(seeds)
    result.p_raw = wilcoxon_above(differences, 0.0)
    result.threshold_met = float(np.mean(tails_on)) >= H6_LAST5_MIN
    result.detail = (
        f"higher with annealing on {sum(d > 0 for d in differences)}, lower on "
        f"{sum(d < 0 for d in differences)}, equal on {sum(d == 0 for d in differences)} seeds"
    )
    result.estimates = [
        *_means("annealed HF last-5 SPL", tails_on),
        *_means("constant-lr HF last-5 SPL", tails_off),
        *_means("last-5 difference", differences, unit="SPL difference"),
    ]
    return result


def h6_accel(task: str, annealed: Sequence[RunRecord] | None) -> HypothesisResult:
    """H1's acceleration under annealing: both methods with ``anneal_lr``."""
    result = HypothesisResult(
        f"H6{_suffix(task)}-accel",
        task,
        "with anneal_lr for both, HF+sparse (virtual subject, decoder 0.6, soft) reaches "
        "SPL 0.7 in fewer steps than RL-sparse",
        _ACCELERATION_TEST,
        ">= 17/20 annealed HF runs reach 0.7",
        seeds=H6_SEEDS,
        family_size=len(H6_FAMILY),
    )
    return _acceleration(result, annealed, last_five_min=None)


def analyse_h6(
    annealed: Sequence[RunRecord] | None, constant: Sequence[RunRecord] | None
) -> list[HypothesisResult]:
    """The second family (H6), in :data:`H6_FAMILY`'s order, Holm-adjusted within it."""
    results = []
    for task in TASKS:
        results += [h6_last5(task, annealed, constant), h6_accel(task, annealed)]
    adjust(results)
    return results


def _means(label: str, values: Sequence[float], unit: str = "SPL") -> list[Estimate]:
    """A mean estimate, or none for fewer than two values (no bootstrap interval)."""
    return [mean_estimate(label, values, unit)] if len(values) >= 2 else []


def adjust(results: Sequence[HypothesisResult]) -> None:
    """Set ``p_holm`` (Holm over the complete hypotheses with data, all of one family) and
    ``p_family_bound`` (Bonferroni over the registered family) of every complete one."""
    complete = [(r, r.p_raw) for r in results if r.complete and r.p_raw is not None]
    adjusted = holm_adjust([p_raw for _, p_raw in complete])
    for (result, p_raw), p in zip(complete, adjusted, strict=True):
        result.p_holm = p
        result.p_family_bound = min(1.0, result.family_size * p_raw)


def analyse(
    e2e: Sequence[RunRecord] | None,
    sil_on: Sequence[RunRecord] | None,
    sil_off: Sequence[RunRecord] | None,
    nstar_rows: Sequence[dict[str, Any]] | None,
    information_rows: Sequence[dict[str, Any]] | None,
) -> list[HypothesisResult]:
    """Every registered hypothesis, in the family's order, Holm-adjusted (None: not run)."""
    results = [h1(task, e2e) for task in TASKS]
    results += [h2(task, sil_on, sil_off) for task in TASKS]
    results += [h3(task, nstar_rows) for task in TASKS]
    results += [h4(task, nstar_rows) for task in TASKS]
    results.append(h5(information_rows))
    adjust(results)
    return results


def _p(value: float | None) -> str:
    if value is None:
        return "-"
    return f"{value:.2g}" if value < 0.001 else f"{value:.3f}"


def markdown_table(results: Sequence[HypothesisResult]) -> str:
    """The table docs/protocol.md asks for: raw and Holm p, estimates with intervals, verdict."""
    size = results[0].family_size if results else len(FAMILY)
    lines = [
        f"| hypothesis | task | test | seeds | raw p | Holm p (with data) | bound over {size} "
        f"({size} p) "
        "| counts and means [95 % interval] | threshold | met | verdict |",
        "|---|---|---|---:|---:|---:|---:|---|---|---|---|",
    ]
    for r in results:
        estimates = "; ".join(e.text() for e in r.estimates) or r.missing or "-"
        if r.detail:
            estimates += f" ({r.detail})"
        met = "-" if r.threshold_met is None else ("yes" if r.threshold_met else "no")
        lines.append(
            f"| {r.hypothesis} | {(r.task or '-').upper()} | {r.test} | {r.n} "
            f"| {_p(r.p_raw)} | {_p(r.p_holm)} | {_p(r.p_family_bound)} | {estimates} "
            f"| {r.threshold} | {met} | {r.verdict} |"
        )
    missing = [r.hypothesis for r in results if r.missing is not None]
    if missing:
        lines.append("")
        lines.append(f"Not run: {', '.join(missing)} (no rows in the stored results).")
    return "\n".join(lines) + "\n"


def plot_estimates(results: Sequence[HypothesisResult], kind: str, path: Path) -> Path | None:
    """Counts (share with Wilson bars) or means (bootstrap bars), one panel per unit; None
    when no hypothesis has an estimate of that kind."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = [
        (r, e) for r in results for e in r.estimates if e.kind == kind
    ]  # in the family's order
    if not points:
        return None
    names = list(dict.fromkeys(r.hypothesis for r in results))
    units = list(dict.fromkeys(e.unit for _, e in points)) if kind == "mean" else ["share"]
    widths = [max(2, sum(1 for _, e in points if kind == "count" or e.unit == u)) for u in units]
    fig, axes = plt.subplots(
        1, len(units), figsize=(max(6.0, 2.0 + 0.45 * sum(widths)), 4.8), squeeze=False,
        gridspec_kw={"width_ratios": widths},
    )  # fmt: skip
    for ax, unit in zip(axes[0], units, strict=True):
        mine = [(r, e) for r, e in points if kind == "count" or e.unit == unit]
        x = np.arange(len(mine))
        values = np.array([e.value for _, e in mine])
        # clipped at 0: the mean of equal values can round just outside its own interval
        low = np.clip(values - np.array([e.low for _, e in mine]), 0.0, None)
        high = np.clip(np.array([e.high for _, e in mine]) - values, 0.0, None)
        colours = [f"C{names.index(r.hypothesis) % 10}" for r, _ in mine]
        ax.bar(x, values, color=colours, alpha=0.7)
        ax.errorbar(x, values, yerr=[low, high], fmt="none", ecolor="black", capsize=3)
        ax.set_xticks(x)
        ax.set_xticklabels(
            [f"{r.hypothesis} {e.label}" for r, e in mine], rotation=60, ha="right", fontsize=7
        )
        if kind == "count":
            ax.set_ylabel("share of seeds (Wilson 95 %)")
            ax.set_ylim(0, 1.05)
            ax.axhline(H1_REACH_SHARE, color="grey", linestyle=":", linewidth=1)
            ax.axhline(USEFUL_SHARE, color="grey", linestyle="--", linewidth=1)
        else:
            ax.set_ylabel(f"mean {unit} (bootstrap 95 %)")
            if unit == "ratio":
                ax.axhline(H5_RATIO, color="grey", linestyle="--", linewidth=1)
            if unit == "SPL":
                ax.set_ylim(0, 1.05)
                ax.axhline(H1_LAST5_MIN, color="grey", linestyle=":", linewidth=1)
            if unit == "SPL difference":
                ax.axhline(0.0, color="grey", linestyle="-", linewidth=1)
        ax.grid(axis="y", alpha=0.3)
    title = (
        "confirmatory counts (dotted 17/20, dashed 16/20)"
        if kind == "count"
        else "confirmatory means (dotted: last-5 0.8; dashed: ratio 1.5)"
    )
    seeds = points[0][0].seeds
    fig.suptitle(f"{title}\nconfirmatory seeds {seeds[0]}-{seeds[-1]}", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def results_json(results: Sequence[HypothesisResult]) -> list[dict[str, Any]]:
    """JSON-able rows of the analysis."""
    from dataclasses import asdict

    return [{**asdict(r), "verdict": r.verdict} for r in results]
