"""N*(C): labels needed for a useful pi_HF (greedy SPL >= 0.5) in >= 80 % of runs (issue #24).

One stage-2 collection per (task, C, seed, method, feedback, label channel) runs to the
largest budget; after the label that completes each smaller budget, a copy of the learner
is finished (the ``bayes`` methods' final fit; nothing for the others) and its greedy pi_HF
evaluated on the task's evaluation starts. A budget's labels are the first labels of a
larger one (the collection never looks at the budget), so each measurement equals that of
a run with that budget (``bgrl hf-sweep``'s ``greedy_spl``), at the cost of the largest
budget alone.

The labels come from the noisy oracle at accuracy C (hard labels; rows made before other
feedback existed are these) or from the virtual subject decoded end to end, C then being the
target held-out accuracy of its decoder, read through the ``hard`` or the ``soft`` channel
(:func:`services.learner.runs.decoded_source`, the same source as ``bgrl hf-sweep``). The two
channels cannot share one collection: the learner chooses the next action from what it has
read, so the trajectories part after the first label; they run as two collections of the
same subject, decoder and seed.

Beside the measured success counts (Wilson 95 % intervals) the figure draws the idealised
Bayesian reference on the oracle's path states (:mod:`services.learner.bayes_reference`)
and the information bound per channel: 30.1 bits over the hard label's ``1 - H(C)``, and
over the bits per label measured for each channel by ``bgrl eeg information`` where given.
"""

from __future__ import annotations

import copy
import functools
import json
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import closing
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np

from services.core.files import write_bytes_atomic
from services.learner.bayes_reference import (
    REFERENCE_RULES,
    identified_fraction,
    information_bound,
    oracle_path,
    path_bits,
)
from services.learner.evaluation import eval_seeds, evaluate_spl
from services.learner.feedback import FeedbackLearner, HFPolicy
from services.learner.feedback_sources import (
    FEEDBACK_SOURCE,
    FeedbackSourceFactory,
    one_feedback_source,
)
from services.learner.runs import HFPolicySpec, decoded_source, feedback_fields, learn_hf_policy
from services.learner.specs import N_VSSG_EVAL_STARTS, TASK_ENV_IDS
from services.learner.stage2_report import USEFUL_SPL
from services.learner.stats import wilson_interval

SUCCESS_SHARE = 0.8
"""N* is the smallest budget at which at least this share of runs has a useful pi_HF."""
PATH_BITS_ISSUE = 30.1
"""The issue's bits to identify the path: 19 states, uniform over 3 actions (19 log2 3)."""


@dataclass(frozen=True)
class NStarJob:
    """One collection: task, C, seed, method, the budgets measured on the way, and where the
    labels come from (as :class:`~services.learner.runs.HFPolicySpec`: ``accuracy`` is the
    oracle's C or None, ``decoder_accuracy`` the virtual subject's target or None)."""

    task: str
    accuracy: float | None
    seed: int
    method: str
    budgets: tuple[int, ...]
    feedback: str = "oracle"
    label_channel: str = "hard"
    decoder_accuracy: float | None = None

    def __post_init__(self) -> None:
        if not self.budgets or min(self.budgets) < 1:
            raise ValueError(f"budgets must be integers >= 1, got {self.budgets}")
        self.spec(max(self.budgets))  # the sweep's checks of the feedback fields

    def spec(self, n_labels: int) -> HFPolicySpec:
        """The ``bgrl hf-sweep`` run this collection equals at budget ``n_labels``."""
        return HFPolicySpec(
            self.task,
            self.accuracy,
            self.seed,
            n_labels,
            self.method,
            self.feedback,
            self.label_channel,
            self.decoder_accuracy,
        )

    @property
    def key(self) -> tuple[Any, ...]:
        """Identity in ``nstar_rows.json`` (the oracle's keys are those of the rows made
        before other feedback existed)."""
        key = (self.task, self.accuracy, self.seed, self.method)
        if self.feedback == "oracle":
            return key
        return (*key, self.feedback, self.label_channel, self.decoder_accuracy)


def row_key(row: dict[str, Any]) -> tuple[Any, ...]:
    """The :attr:`NStarJob.key` of a row (a row without ``feedback`` is the oracle's)."""
    key = (row["task"], row["accuracy"], row["seed"], row["method"])
    if row.get("feedback", "oracle") == "oracle":
        return key
    return (*key, row["feedback"], row["label_channel"], row["decoder_accuracy_target"])


def row_c(row: dict[str, Any]) -> float:
    """A row's C: the oracle's accuracy, or the target accuracy of the subject's decoder."""
    if row.get("feedback", "oracle") == "oracle":
        return float(row["accuracy"])
    return float(row["decoder_accuracy_target"])


def nstar_run(
    job: NStarJob, feedback_factory: FeedbackSourceFactory | None = None
) -> list[dict[str, Any]]:
    """Collect up to ``max(job.budgets)`` labels; one row per budget with the greedy SPL
    and the feedback fields of ``bgrl hf-sweep``'s rows (``feedback_factory`` makes the
    virtual subject's source)."""
    import torch

    torch.set_num_threads(1)
    rows: list[dict[str, Any]] = []
    start = time.perf_counter()
    budgets = set(job.budgets)
    source = decoded_source(job.feedback, job.seed, job.decoder_accuracy, feedback_factory)
    with (
        closing(gym.make(TASK_ENV_IDS[job.task], reward_mode="sparse")) as env,
        closing(gym.make(TASK_ENV_IDS[job.task], reward_mode="sparse")) as eval_env,
    ):
        seeds = eval_seeds(job.task, N_VSSG_EVAL_STARTS)

        def measure(learner: FeedbackLearner) -> None:
            n = len(learner.buffer) + len(learner.validation)
            if n not in budgets:
                return
            finished = copy.deepcopy(learner)
            finished.finish()
            policy = HFPolicy(finished.model, finished.config.beta, job.method)
            rows.append(
                {
                    "task": job.task,
                    "accuracy": job.accuracy,
                    "seed": job.seed,
                    "method": job.method,
                    **feedback_fields(True, job.spec(n), source),
                    "decoder_accuracy_target": job.decoder_accuracy,
                    "greedy_spl": evaluate_spl(eval_env, policy.act, seeds),
                    "wall_seconds": time.perf_counter() - start,
                }
            )

        hf = learn_hf_policy(
            env,
            job.accuracy,  # type: ignore[arg-type]  # None only with a source
            job.seed,
            max(job.budgets),
            method=job.method,
            source=source,
            label_channel=job.label_channel,
            on_learner=measure,
        )
    for row in rows:
        row["n_steps_total"] = hf.n_steps
    return rows


class RowsFile(NamedTuple):
    """What an ``nstar_rows.json`` holds."""

    rows: list[dict[str, Any]]
    feedback_source: dict[str, Any] | None
    """The virtual subjects' settings (``FeedbackSourceFactory.describe()``); None in a file
    of the oracle's rows alone or written before the record (then the default settings)."""


def load_rows(path: str | Path) -> RowsFile:
    """The rows and feedback-source settings of an ``nstar_rows.json``: ``{"config":
    {"feedback_source": ...}, "rows": [...]}``, or a list of rows (files written before the
    record). A one-line ValueError naming the file if it is not one (left as it is)."""
    path = Path(path)
    try:
        document = json.loads(path.read_text())
        if isinstance(document, list):
            document = {"rows": document}
        rows = document["rows"]
        source = document.get("config", {}).get(FEEDBACK_SOURCE)
        if not isinstance(rows, list):
            raise TypeError("rows is not a list")
        if not isinstance(source, dict | None):
            raise TypeError(f"config.{FEEDBACK_SOURCE} is not an object")
        for row in rows:
            row_key(row)
            for name in ("n_labels", "greedy_spl"):  # what the table reads
                if not isinstance(row[name], int | float):
                    raise TypeError(f"{name} is not a number")
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read it ({exc})") from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a `bgrl hf-nstar` rows file ({exc!r})") from None
    return RowsFile(rows, source)


def run_jobs(
    jobs: Sequence[NStarJob],
    path: Path,
    workers: int = 1,
    on_done: Callable[[NStarJob, list[dict[str, Any]]], None] | None = None,
    feedback_factory: FeedbackSourceFactory | None = None,
) -> list[dict[str, Any]]:
    """Run the jobs not yet in ``path`` (:func:`load_rows`; rewritten after each job) and
    return its rows. ``path`` records the virtual subjects' settings (``feedback_source``:
    ``feedback_factory.describe()``) and holds rows of one set: a file that is not one, or
    virtual-subject rows made with other settings, is a ValueError naming it before anything
    runs."""
    rows, recorded = load_rows(path) if path.exists() else ([], None)
    source = one_feedback_source(
        path.parent,
        recorded,
        (row.get("feedback", "oracle") for row in rows),
        (job.feedback for job in jobs),
        feedback_factory,
    )
    config = {} if source is None else {FEEDBACK_SOURCE: source}
    done = {row_key(r) for r in rows}
    todo = [job for job in jobs if job.key not in done]
    run = functools.partial(nstar_run, feedback_factory=feedback_factory)
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for job, new in zip(todo, pool.map(run, todo), strict=True):
            rows.extend(new)
            # atomically: a kill mid-write leaves the previous rows, never half a file
            write_bytes_atomic(
                path, json.dumps({"config": config, "rows": rows}, indent=1).encode()
            )
            if on_done is not None:
                on_done(job, new)
    return rows


SeriesKey = tuple[str, str, str, str, float]
"""(method, task, feedback, label_channel, C): one line of the table and of the figure."""


def series_key(row: dict[str, Any]) -> SeriesKey:
    """A row's series; rows without feedback fields are the oracle's hard labels."""
    return (
        row["method"],
        row["task"],
        row.get("feedback", "oracle"),
        row.get("label_channel", "hard"),
        row_c(row),
    )


def success_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (method, task, feedback, channel, C, budget): runs, runs with a useful pi_HF,
    Wilson 95 %, mean greedy SPL and, for the virtual subject, the decoders' mean measured
    held-out accuracy (``accuracy`` is C: the oracle's, or the decoder's target)."""
    groups: dict[tuple[SeriesKey, int], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((series_key(row), row["n_labels"]), []).append(row)
    table = []
    for ((method, task, feedback, channel, c), n), members in sorted(groups.items()):
        spls = [r["greedy_spl"] for r in members]
        decoded = [r["decoder_accuracy"] for r in members if r.get("decoder_accuracy") is not None]
        useful = int(sum(s >= USEFUL_SPL for s in spls))
        low, high = wilson_interval(useful, len(spls))
        table.append(
            {
                "method": method,
                "task": task,
                "feedback": feedback,
                "label_channel": channel,
                "accuracy": c,
                "decoder_accuracy": float(np.mean(decoded)) if decoded else None,
                "n_labels": n,
                "runs": len(spls),
                "useful": useful,
                "share": useful / len(spls),
                "wilson_low": low,
                "wilson_high": high,
                "mean_spl": float(np.mean(spls)),
            }
        )
    return table


def _series(row: dict[str, Any]) -> SeriesKey:
    return (row["method"], row["task"], row["feedback"], row["label_channel"], row["accuracy"])


def n_star(table: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Smallest measured budget with a useful share >= 0.8 per (method, task, feedback,
    channel, C), or None (``above`` gives the largest budget measured)."""
    out: dict[SeriesKey, dict[str, Any]] = {}
    for row in table:
        key = _series(row)
        entry = out.setdefault(
            key,
            {
                "method": key[0],
                "task": key[1],
                "feedback": key[2],
                "label_channel": key[3],
                "accuracy": key[4],
                "decoder_accuracy": row["decoder_accuracy"],
                "n_star": None,
                "above": 0,
            },
        )
        entry["above"] = max(entry["above"], row["n_labels"])
        if row["share"] >= SUCCESS_SHARE and (
            entry["n_star"] is None or row["n_labels"] < entry["n_star"]
        ):
            entry["n_star"] = row["n_labels"]
    return list(out.values())


def series_label(entry: dict[str, Any]) -> str:
    """E.g. ``bayes_query sssg C=0.6`` (oracle) or ``bayes_query sssg subject@0.6 soft``."""
    where = (
        f"C={entry['accuracy']:g}"
        if entry["feedback"] == "oracle"
        else f"subject@{entry['accuracy']:g} {entry['label_channel']}"
    )
    return f"{entry['method']} {entry['task']} {where}"


def reference_curves(
    task: str,
    accuracies: Sequence[float],
    budgets: Sequence[int],
    draws: int = 400,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """The idealised reference on the task's oracle path: identified share per rule, C and
    budget, and N* (first budget of ``budgets`` with share >= 0.8)."""
    mask = oracle_path(task)
    out = []
    for accuracy in accuracies:
        for rule in REFERENCE_RULES:
            shares = identified_fraction(mask, accuracy, budgets, rule, draws, seed)
            reached = [n for n, share in sorted(shares.items()) if share >= SUCCESS_SHARE]
            out.append(
                {
                    "task": task,
                    "accuracy": accuracy,
                    "rule": rule,
                    "draws": draws,
                    "identified": {str(n): s for n, s in shares.items()},
                    "n_star": reached[0] if reached else None,
                }
            )
    return out


def bounds(
    task: str,
    accuracies: Sequence[float],
    information: Sequence[dict[str, Any]] = (),
) -> list[dict[str, Any]]:
    """The information bound per C: the path's bits (uniform prior, ties counted) and the
    issue's 30.1 bits over the hard label's ``1 - H(C)``; where ``information`` (the
    ``summary`` of ``bgrl eeg information``) measured subjects decoded at target C, also
    30.1 bits over each channel's measured bits per label (``soft_30_1``, None elsewhere),
    at the accuracy the subjects' decoders reached (``measured_accuracy``)."""
    bits = path_bits(oracle_path(task))
    out = []
    for c in accuracies:
        row: dict[str, Any] = {
            "task": task,
            "accuracy": c,
            "path_bits": bits,
            "hard_30_1": information_bound(PATH_BITS_ISSUE, c),
            "hard_path": information_bound(bits, c),
            "measured_accuracy": None,
            "hard_bits": None,
            "soft_bits": None,
            "soft_30_1": None,
        }
        for measured in information:
            if math.isclose(measured["target_accuracy"], c):
                row |= {
                    "measured_accuracy": measured["accuracy"],
                    "subjects": measured["subjects"],
                    "hard_bits": measured["hard_bits_bsc"],
                    "soft_bits": measured["soft_information"],
                    "hard_measured_30_1": PATH_BITS_ISSUE / measured["hard_bits_bsc"],
                    "soft_30_1": PATH_BITS_ISSUE / measured["soft_information"],
                }
        out.append(row)
    return out


CHANNEL_STYLES = {"hard": "-", "soft": "--"}


def plot_nstar(
    table: Sequence[dict[str, Any]],
    stars: Sequence[dict[str, Any]],
    reference: Sequence[dict[str, Any]],
    limits: Sequence[dict[str, Any]],
    path: Path,
) -> None:
    """One panel per feedback and channel: useful share vs labels at each C (Wilson 95 %),
    with the reference's identified share on the hard panels; last panel: N*(C) per method,
    task and channel (the virtual subject's at its decoders' measured accuracy), the
    reference's and the bound per channel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    channels = sorted({(row["feedback"], row["label_channel"]) for row in table}) or [
        ("oracle", "hard")
    ]
    accuracies = sorted({row["accuracy"] for row in table} | {r["accuracy"] for r in limits})
    colours = dict(
        zip(accuracies, plt.cm.viridis(np.linspace(0, 0.9, len(accuracies))), strict=True)
    )
    markers = {m: "os^vD"[k % 5] for k, m in enumerate(sorted({row["method"] for row in table}))}
    fig, axes = plt.subplots(1, len(channels) + 1, figsize=(6.5 * (len(channels) + 1), 5.5))
    series: dict[SeriesKey, list[dict[str, Any]]] = {}
    for row in table:
        series.setdefault(_series(row), []).append(row)
    for ax, (feedback, channel) in zip(axes, channels, strict=False):
        for (method, task, fb, ch, c), points in sorted(series.items()):
            if (fb, ch) != (feedback, channel):
                continue
            ax.errorbar(
                [p["n_labels"] for p in points],
                [p["share"] for p in points],
                yerr=[
                    [p["share"] - p["wilson_low"] for p in points],
                    [p["wilson_high"] - p["share"] for p in points],
                ],
                marker=markers[method],
                capsize=3,
                color=colours[c],
                linestyle="-" if task == "sssg" else "--",
                label=f"{method} {task.upper()} C={c:g}",
            )
        if channel == "hard":  # the reference reads hard labels of accuracy C
            for ref in reference:
                if ref["rule"] == "adaptive_forward":
                    pts = sorted((int(n), s) for n, s in ref["identified"].items())
                    ax.plot(
                        *zip(*pts, strict=True),
                        color=colours.get(ref["accuracy"], "grey"),
                        linestyle=":",
                        alpha=0.8,
                    )
        ax.axhline(SUCCESS_SHARE, color="grey", linewidth=0.8)
        what = "noisy oracle" if feedback == "oracle" else "virtual subject"
        ax.set(
            xscale="log",
            xlabel="labels" + ("" if feedback == "oracle" else " (C: the decoder's target)"),
            ylabel="share of runs with greedy SPL >= 0.5",
            title=f"{what}, {channel} labels (Wilson 95 %)"
            + ("; dotted: reference" if channel == "hard" else ""),
            ylim=(-0.02, 1.02),
        )
        ax.legend(fontsize=6, ncol=2)
    _plot_n_star(axes[-1], stars, reference, limits)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_n_star(
    ax: Any,
    stars: Sequence[dict[str, Any]],
    reference: Sequence[dict[str, Any]],
    limits: Sequence[dict[str, Any]],
) -> None:
    """N* against C: the bound per channel, the reference's and each series' (hollow: above
    the largest budget measured)."""
    limits = sorted({r["accuracy"]: r for r in limits}.values(), key=lambda r: r["accuracy"])
    cs = [r["accuracy"] for r in limits]
    ax.plot(cs, [r["hard_30_1"] for r in limits], "k-", label="bound 30.1 bits / (1 - H(C))")
    hard = [(r["measured_accuracy"], r["hard_measured_30_1"]) for r in limits if r["hard_bits"]]
    if hard:
        ax.plot(*zip(*hard, strict=True), "k+", markersize=9,
                label="bound, hard: 30.1 bits / measured 1 - H(error rate)")  # fmt: skip
    soft = [(r["measured_accuracy"], r["soft_30_1"]) for r in limits if r["soft_30_1"]]
    if soft:
        ax.plot(*zip(*soft, strict=True), "k--", marker="x",
                label="bound, soft: 30.1 bits / measured bits per label")  # fmt: skip
    for rule, style in (("adaptive", "v:"), ("adaptive_forward", "^:"), ("round_robin", "x:")):
        pts = [(r["accuracy"], r["n_star"]) for r in reference if r["rule"] == rule and r["n_star"]]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=f"reference {rule} (hard)")
    lines = dict.fromkeys(
        (s["method"], s["task"], s["feedback"], s["label_channel"]) for s in stars
    )
    colours = {}
    for method, task, feedback, channel in lines:
        members = [
            s
            for s in stars
            if (s["method"], s["task"], s["feedback"], s["label_channel"])
            == (method, task, feedback, channel)
        ]
        # the virtual subject's point stands at its decoders' measured accuracy
        found = sorted(
            (s["decoder_accuracy"] or s["accuracy"], s["n_star"]) for s in members if s["n_star"]
        )
        above = sorted(
            (s["decoder_accuracy"] or s["accuracy"], s["above"]) for s in members if not s["n_star"]
        )
        name = (
            f"{method} {task.upper()} {'oracle' if feedback == 'oracle' else 'subject'} {channel}"
        )
        colour = colours.setdefault((method, task), f"C{len(colours) + 3}")  # C0-C2: reference
        marker = "o" if feedback == "oracle" else "s"
        if found:
            ax.plot(*zip(*found, strict=True), marker=marker, color=colour,
                    linestyle=CHANNEL_STYLES[channel], label=f"{name}: N*")  # fmt: skip
        if above:
            ax.plot(*zip(*above, strict=True), marker="^", color=colour, linestyle="none",
                    markerfacecolor="none", label=f"{name}: > largest budget")  # fmt: skip
    ax.set(
        yscale="log",
        xlabel="C (oracle accuracy; virtual subject: measured decoder accuracy)",
        ylabel="labels N*",
        title="N*(C): >= 80 % useful pi_HF",
    )
    ax.legend(fontsize=6)


def markdown_table(table: Sequence[dict[str, Any]], stars: Sequence[dict[str, Any]]) -> str:
    """One line per (method, task, feedback, channel, C): useful runs / runs at each budget
    with the Wilson 95 % interval, and N*."""
    found = {_series(s): s for s in stars}
    cells: dict[SeriesKey, list[str]] = {}
    for row in table:
        cells.setdefault(_series(row), []).append(
            f"{row['n_labels']}: {row['useful']}/{row['runs']} "
            f"({row['wilson_low']:.0%}-{row['wilson_high']:.0%})"
        )
    lines = [
        "| method | task | feedback | channel | C | decoded acc. "
        "| useful pi_HF at each budget (Wilson 95 %) | N* |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, entries in cells.items():
        star = found[key]
        n = str(star["n_star"]) if star["n_star"] else f"> {star['above']}"
        decoded = "" if star["decoder_accuracy"] is None else f"{star['decoder_accuracy']:.3f}"
        lines.append(
            f"| {key[0]} | {key[1].upper()} | {key[2]} | {key[3]} | {key[4]:g} | {decoded} "
            f"| {'; '.join(entries)} | {n} |"
        )
    return "\n".join(lines) + "\n"


def write_outputs(
    out: Path,
    rows: Sequence[dict[str, Any]],
    reference: Sequence[dict[str, Any]],
    limits: Sequence[dict[str, Any]],
    figure: Path | None = None,
) -> dict[str, Any]:
    """``nstar.json`` (table, N*, reference, bounds), ``nstar.csv`` and ``nstar.md`` (the
    table) and ``nstar.png`` (also copied to ``figure``)."""
    import csv
    import shutil

    table = success_table(rows)
    stars = n_star(table)
    result = {"table": table, "n_star": stars, "reference": list(reference), "bounds": list(limits)}
    (out / "nstar.json").write_text(json.dumps(result, indent=1))
    (out / "nstar.md").write_text(markdown_table(table, stars))
    if table:
        with (out / "nstar.csv").open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    plot_nstar(table, stars, reference, limits, out / "nstar.png")
    if figure is not None:
        figure.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "nstar.png", figure)
    return result


def job_dicts(jobs: Sequence[NStarJob]) -> list[dict[str, Any]]:
    """JSON-able jobs."""
    return [asdict(job) for job in jobs]
