"""N*(C): labels needed for a useful pi_HF (greedy SPL >= 0.5) in >= 80 % of runs (issue #24).

One stage-2 collection per (task, C, seed, method) runs to the largest budget; after the
label that completes each smaller budget, a copy of the learner is finished (the ``bayes``
methods' final fit; nothing for the others) and its greedy pi_HF evaluated on the task's
evaluation starts. A budget's labels are the first labels of a larger one (the collection
never looks at the budget), so each measurement equals that of a run with that budget
(``bgrl hf-sweep``'s ``greedy_spl``), at the cost of the largest budget alone.

Beside the measured success counts (Wilson 95 % intervals) the figure draws the idealised
Bayesian reference on the oracle's path states (:mod:`services.learner.bayes_reference`)
and the information bound.
"""

from __future__ import annotations

import copy
import json
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import closing
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from services.learner.bayes_reference import (
    REFERENCE_RULES,
    identified_fraction,
    information_bound,
    oracle_path,
    path_bits,
)
from services.learner.evaluation import eval_seeds, evaluate_spl
from services.learner.feedback import FeedbackLearner, HFPolicy
from services.learner.runs import learn_hf_policy
from services.learner.specs import N_VSSG_EVAL_STARTS, TASK_ENV_IDS
from services.learner.stage2_report import USEFUL_SPL
from services.learner.stats import wilson_interval

SUCCESS_SHARE = 0.8
"""N* is the smallest budget at which at least this share of runs has a useful pi_HF."""
SOFT_GAIN_AT_0_6 = 1.52
"""The soft channel's bits per label over the hard label's at decoder accuracy 0.606
(``bgrl eeg information``, docs/stage2.md): the soft bound is the hard one over this."""


@dataclass(frozen=True)
class NStarJob:
    """One collection: task, C, seed, method, the budgets measured on the way."""

    task: str
    accuracy: float
    seed: int
    method: str
    budgets: tuple[int, ...]

    @property
    def key(self) -> tuple[Any, ...]:
        return (self.task, self.accuracy, self.seed, self.method)


def nstar_run(job: NStarJob) -> list[dict[str, Any]]:
    """Collect up to ``max(job.budgets)`` labels; one row per budget with the greedy SPL."""
    import torch

    torch.set_num_threads(1)
    rows: list[dict[str, Any]] = []
    start = time.perf_counter()
    budgets = set(job.budgets)
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
                    "n_labels": n,
                    "feedback": "oracle",
                    "label_channel": "hard",
                    "greedy_spl": evaluate_spl(eval_env, policy.act, seeds),
                    "wall_seconds": time.perf_counter() - start,
                }
            )

        hf = learn_hf_policy(
            env, job.accuracy, job.seed, max(job.budgets), method=job.method, on_learner=measure
        )
    for row in rows:
        row["n_steps_total"] = hf.n_steps
    return rows


def run_jobs(
    jobs: Sequence[NStarJob],
    path: Path,
    workers: int = 1,
    on_done: Callable[[NStarJob, list[dict[str, Any]]], None] | None = None,
) -> list[dict[str, Any]]:
    """Run the jobs not yet in ``path`` (a JSON list of rows, rewritten after each job)."""
    rows: list[dict[str, Any]] = json.loads(path.read_text()) if path.exists() else []
    done = {(r["task"], r["accuracy"], r["seed"], r["method"]) for r in rows}
    todo = [job for job in jobs if job.key not in done]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for job, new in zip(todo, pool.map(nstar_run, todo), strict=True):
            rows.extend(new)
            path.write_text(json.dumps(rows, indent=1))
            if on_done is not None:
                on_done(job, new)
    return rows


def success_table(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (method, task, C, budget): runs, runs with a useful pi_HF, Wilson 95 %."""
    groups: dict[tuple[str, str, float, int], list[float]] = {}
    for row in rows:
        key = (row["method"], row["task"], row["accuracy"], row["n_labels"])
        groups.setdefault(key, []).append(row["greedy_spl"])
    table = []
    for (method, task, accuracy, n), spls in sorted(groups.items()):
        useful = int(sum(s >= USEFUL_SPL for s in spls))
        low, high = wilson_interval(useful, len(spls))
        table.append(
            {
                "method": method,
                "task": task,
                "accuracy": accuracy,
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


def n_star(table: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Smallest measured budget with a useful share >= 0.8 per (method, task, C), or None
    (``above`` gives the largest budget measured)."""
    out: dict[tuple[str, str, float], dict[str, Any]] = {}
    for row in table:
        key = (row["method"], row["task"], row["accuracy"])
        entry = out.setdefault(
            key,
            {"method": key[0], "task": key[1], "accuracy": key[2], "n_star": None, "above": 0},
        )
        entry["above"] = max(entry["above"], row["n_labels"])
        if row["share"] >= SUCCESS_SHARE and (
            entry["n_star"] is None or row["n_labels"] < entry["n_star"]
        ):
            entry["n_star"] = row["n_labels"]
    return list(out.values())


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


def bounds(task: str, accuracies: Sequence[float]) -> list[dict[str, Any]]:
    """The information bound per C: the path's bits (uniform prior, ties counted) and the
    19 log2 3 = 30.1 bits of the issue, over the hard label's bits (and the soft's)."""
    bits = path_bits(oracle_path(task))
    return [
        {
            "task": task,
            "accuracy": c,
            "path_bits": bits,
            "hard_30_1": information_bound(30.1, c),
            "hard_path": information_bound(bits, c),
            "soft_30_1": information_bound(30.1, c, SOFT_GAIN_AT_0_6),
        }
        for c in accuracies
    ]


def plot_nstar(
    table: Sequence[dict[str, Any]],
    stars: Sequence[dict[str, Any]],
    reference: Sequence[dict[str, Any]],
    limits: Sequence[dict[str, Any]],
    path: Path,
) -> None:
    """Left: useful share vs labels at each C (Wilson 95 %) with the reference's identified
    share; right: N*(C) per method and task, the reference's and the bound."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    accuracies = sorted({row["accuracy"] for row in table} | {r["accuracy"] for r in limits})
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    ax = axes[0]
    colours = dict(
        zip(accuracies, plt.cm.viridis(np.linspace(0, 0.9, len(accuracies))), strict=True)
    )
    series: dict[tuple[str, str, float], list[dict[str, Any]]] = {}
    for row in table:
        series.setdefault((row["method"], row["task"], row["accuracy"]), []).append(row)
    markers = {m: "os^vD"[k % 5] for k, m in enumerate(sorted({row["method"] for row in table}))}
    for (method, task, c), points in sorted(series.items()):
        xs = [p["n_labels"] for p in points]
        ys = [p["share"] for p in points]
        err = [
            [p["share"] - p["wilson_low"] for p in points],
            [p["wilson_high"] - p["share"] for p in points],
        ]
        ax.errorbar(
            xs,
            ys,
            yerr=err,
            marker=markers[method],
            capsize=3,
            color=colours[c],
            linestyle="-" if task == "sssg" else "--",
            label=f"{method} {task.upper()} C={c:g}",
        )
    for ref in reference:
        if ref["rule"] != "adaptive_forward":
            continue
        pts = sorted((int(n), s) for n, s in ref["identified"].items())
        ax.plot(
            *zip(*pts, strict=True),
            color=colours.get(ref["accuracy"], "grey"),
            linestyle=":",
            alpha=0.8,
        )
    ax.axhline(SUCCESS_SHARE, color="grey", linewidth=0.8)
    ax.set(
        xscale="log",
        xlabel="labels",
        ylabel="share of runs with greedy SPL >= 0.5",
        title="useful pi_HF (Wilson 95 %); dotted: idealised reference (forward prior)",
        ylim=(-0.02, 1.02),
    )
    ax.legend(fontsize=6, ncol=2)
    ax = axes[1]
    limits = list({r["accuracy"]: r for r in limits}.values())  # 30.1 bits: same per task
    cs = [r["accuracy"] for r in limits]
    ax.plot(cs, [r["hard_30_1"] for r in limits], "k-", label="bound 30.1 bits / (1 - H(C))")
    ax.plot(cs, [r["soft_30_1"] for r in limits], "k--", label="bound, soft channel (1.52x bits)")
    for rule, style in (("adaptive", "v:"), ("adaptive_forward", "^:"), ("round_robin", "x:")):
        pts = [(r["accuracy"], r["n_star"]) for r in reference if r["rule"] == rule and r["n_star"]]
        if pts:
            ax.plot(*zip(*pts, strict=True), style, label=f"reference {rule}")
    for method, task in dict.fromkeys((s["method"], s["task"]) for s in stars):
        found = [
            (s["accuracy"], s["n_star"])
            for s in stars
            if (s["method"], s["task"]) == (method, task) and s["n_star"]
        ]
        above = [
            (s["accuracy"], s["above"])
            for s in stars
            if (s["method"], s["task"]) == (method, task) and not s["n_star"]
        ]
        line = (
            ax.plot(*zip(*found, strict=True), "o-", label=f"{method} {task.upper()} N*")[0]
            if found
            else None
        )
        if above:
            ax.plot(
                *zip(*above, strict=True),
                "^",
                color=line.get_color() if line else None,
                markerfacecolor="none",
                label=f"{method} {task.upper()}: > largest budget",
            )
    ax.set(
        yscale="log",
        xlabel="C (label accuracy)",
        ylabel="labels N*",
        title="N*(C): >= 80 % useful pi_HF",
    )
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown_table(table: Sequence[dict[str, Any]], stars: Sequence[dict[str, Any]]) -> str:
    """One line per (method, task, C): useful runs / runs at each budget with the Wilson 95 %
    interval, and N*."""
    found = {(s["method"], s["task"], s["accuracy"]): s for s in stars}
    cells: dict[tuple[str, str, float], list[str]] = {}
    for row in table:
        cells.setdefault((row["method"], row["task"], row["accuracy"]), []).append(
            f"{row['n_labels']}: {row['useful']}/{row['runs']} "
            f"({row['wilson_low']:.0%}-{row['wilson_high']:.0%})"
        )
    lines = [
        "| method | task | C | useful pi_HF at each budget (Wilson 95 %) | N* |",
        "|---|---|---|---|---|",
    ]
    for key, entries in cells.items():
        star = found[key]
        n = str(star["n_star"]) if star["n_star"] else f"> {star['above']}"
        lines.append(f"| {key[0]} | {key[1].upper()} | {key[2]:g} | {'; '.join(entries)} | {n} |")
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
