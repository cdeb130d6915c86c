"""Files of a reproduction: ``results.json``, the CSV, summary tables, Fig. 3 and comparisons.

``results.json`` is ``{"config": ..., "runs": [RunRecord...], "failed": [RunFailure...]}``;
folders written before failures were recorded have no ``failed`` key and load the same.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from services.core.files import write_json_atomic
from services.learner.runs import RunFailure, RunRecord
from services.learner.stats import group_label, paper_claims, sort_key, summarize


@dataclass
class Results:
    """The content of a ``results.json``."""

    config: dict[str, Any]
    runs: list[RunRecord] = field(default_factory=list)
    failed: list[RunFailure] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form."""
        return {
            "config": self.config,
            "runs": [r.to_dict() for r in self.runs],
            "failed": [f.to_dict() for f in self.failed],
        }


def load_results(path: str | Path) -> Results:
    """Read a ``results.json``; a one-line ValueError naming it if it is missing, a folder,
    unreadable or not one."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(
            f"{path}: a folder, not a results file (move it away or use another --out)"
        )
    if not path.is_file():
        raise ValueError(f"{path.parent}: no results.json (not a `bgrl reproduce` folder)")
    try:
        data = json.loads(path.read_text())
        return Results(
            config=data["config"],
            runs=[RunRecord.from_dict(r) for r in data["runs"]],
            failed=[RunFailure.from_dict(f) for f in data.get("failed", [])],
        )
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read it ({exc})") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not a reproduction results file ({exc})") from None


def save_results(path: str | Path, results: Results) -> None:
    """Write ``results.json`` atomically."""
    write_json_atomic(path, results.to_dict(), indent=1)


def write_outputs(out: Path, runs: Sequence[RunRecord]) -> None:
    """``results.csv``, ``summary.md`` / ``summary.json`` (with the claims) and Fig. 3 plots."""
    write_csv(out / "results.csv", runs)
    summary = summarize(runs)
    claims = paper_claims(summary)
    (out / "summary.md").write_text(summary_markdown(summary) + "\n" + claims_markdown(claims))
    write_json_atomic(out / "summary.json", {"groups": summary, "claims": claims}, indent=1)
    plot_figure3(runs, out)


def write_csv(path: Path, runs: Sequence[RunRecord]) -> None:
    """One row per run (the curve flattened to ``step:spl`` pairs)."""
    fields = [
        "task", "method", "hf_treatment", "accuracy", "feedback", "label_channel",
        "decoder_accuracy", "subject_quality", "seed", "final_spl", "hf_policy_spl",
        "steps_to_0_7", "wall_seconds", "curve",
    ]  # fmt: skip
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for run in sorted(runs, key=sort_key):
            row = {k: getattr(run, k) for k in fields}
            row["curve"] = " ".join(f"{step}:{spl:.3f}" for step, spl in run.curve)
            writer.writerow(row)


def summary_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The summary as a Markdown table."""

    def fmt(value: Any, digits: int = 2) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "-"
        return f"{value:.{digits}f}" if isinstance(value, float) else str(value)

    lines = [
        "| task | method | seeds | final SPL mean ± std | last-5-eval SPL mean ± std | "
        "mean SPL over training | max of mean curve | mean curve reaches 0.7 at | "
        "runs reaching 0.7 | median steps to 0.7 | HF policy SPL |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        hf = (
            "-"
            if r["hf_policy_spl_mean"] is None
            else f"{r['hf_policy_spl_mean']:.2f} ± {r['hf_policy_spl_std']:.2f}"
        )
        lines.append(
            f"| {r['task'].upper()} | {r['group']} | {r['n_seeds']} | "
            f"{r['final_spl_mean']:.2f} ± {r['final_spl_std']:.2f} | "
            f"{r['last5_spl_mean']:.2f} ± {r['last5_spl_std']:.2f} | "
            f"{np.mean(r['mean_spl_over_training']):.2f} | {r['max_mean_curve_spl']:.2f} | "
            f"{fmt(r['mean_curve_steps_to_0_7'])} | "
            f"{r['runs_reaching_0_7']}/{r['n_seeds']} | {fmt(r['median_steps_to_0_7'], 0)} | "
            f"{hf} |"
        )
    notes = [
        f"- {r['task'].upper()} {r['group']}: decoder held-out accuracy "
        f"{r['decoder_accuracy_mean']:.3f} on average over the subjects"
        + (
            "; outside the target's tolerance (kept): "
            + ", ".join(
                f"seed {m['seed']} {m['decoder_accuracy']:.3f}" for m in r["decoder_off_target"]
            )
            if r["decoder_off_target"]
            else ""
        )
        for r in rows
        if r["decoder_accuracy_mean"] is not None
    ]
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(notes) + "\n" if notes else "")


def claims_markdown(claims: Sequence[dict[str, Any]]) -> str:
    """The claim checks as a Markdown table."""
    verdict = {True: "holds", False: "**does not hold**", None: "-"}
    lines = ["| task | claim | verdict | measured | seeds |", "|---|---|---|---|---|"]
    lines += [
        f"| {c['task'].upper()} | {c['claim']} | {verdict[c['holds']]} | {c['measured']} | "
        f"{c['n_seeds']} |"
        for c in claims
    ]
    return "\n".join(lines) + "\n"


def plot_figure3(runs: Sequence[RunRecord], out_dir: Path) -> list[Path]:
    """Fig. 3-like plots per task: mean +- 1/2 std of SPL vs env steps, HF policy lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for task in sorted({r.task for r in runs}):
        fig, ax = plt.subplots(figsize=(7, 4.5))
        groups: dict[str, list[RunRecord]] = {}
        for run in sorted((r for r in runs if r.task == task), key=sort_key):
            groups.setdefault(group_label(run), []).append(run)
        for index, (label, members) in enumerate(groups.items()):
            color = f"C{index}"
            length = min(len(r.curve) for r in members)
            curves = np.array([r.curve[:length] for r in members], dtype=float)
            steps, spl = curves[0, :, 0], curves[:, :, 1]
            mean, half_std = spl.mean(axis=0), spl.std(axis=0) / 2.0
            ax.plot(steps, mean, color=color, label=f"{label} (n={len(members)})")
            ax.fill_between(steps, mean - half_std, mean + half_std, color=color, alpha=0.2)
            hf = [r.hf_policy_spl for r in members if r.hf_policy_spl is not None]
            if hf:
                ax.axhline(float(np.mean(hf)), color=color, linestyle="--", linewidth=1)
        ax.set_title(f"{task.upper()}: SPL of greedy pi_RL (mean ± ½ std; dashed: pi_HF)")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("SPL")
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
        fig.tight_layout()
        path = out_dir / f"fig3_{task}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def load_study(folder: str | Path) -> tuple[dict[str, Any], list[RunRecord]]:
    """(PPO overrides, runs) of a reproduction folder; a clear error if it is none."""
    results = load_results(Path(folder) / "results.json")
    overrides = dict(results.runs[0].run_spec.ppo_overrides) if results.runs else {}
    return overrides, results.runs


def study_names(folders: Sequence[str | Path]) -> list[str]:
    """Each folder's name, with as many of its parents as it takes to tell the folders apart
    (``jan/study``, ``feb/study``); a ValueError if one folder is given twice."""
    paths = [Path(folder).resolve() for folder in folders]
    for path, folder in zip(paths, folders, strict=True):
        if paths.count(path) > 1:
            raise ValueError(f"{folder}: the same study given twice (its runs would count twice)")

    def tail(path: Path, depth: int) -> str:
        return str(Path(*path.parts[-depth:]))

    names = []
    for path in paths:
        depth = 1  # grows at the latest to the whole path, which no other folder's tail is
        while any(tail(other, depth) == tail(path, depth) for other in paths if other != path):
            depth += 1
        names.append(tail(path, depth))
    return names


def compare_studies(folders: Sequence[str | Path], out_dir: str | Path) -> list[dict[str, Any]]:
    """Factor studies side by side: one :func:`summarize` row per study, task and group.

    A study is named by its folder (with parents where two folders share a name; one
    folder given twice is a ValueError). Writes ``out_dir/compare.md`` (table),
    ``compare.json`` and ``compare_<task>.png``: every
    run's mean SPL over its last five evaluations (dots) with each group's mean ± std, so
    studies that differ in one factor (treatment, guidance, PPO setting) can be read together.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = study_names(folders)  # bad input fails before writing
    studies = [load_study(folder) for folder in folders]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = [
        {"study": name, "ppo_overrides": overrides, **row}
        for name, (overrides, runs) in zip(names, studies, strict=True)
        for row in summarize(runs)
    ]
    lines = [
        "| task | study | PPO overrides | method | seeds | final SPL | last-5 SPL | best SPL | "
        "mean SPL over training | runs reaching 0.7 | median steps to 0.7 | HF policy SPL |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["task"], r["group"], r["study"])):
        override_text = ", ".join(f"{k}={v}" for k, v in sorted(r["ppo_overrides"].items()))
        median = r["median_steps_to_0_7"]
        hf = r["hf_policy_spl_mean"]
        lines.append(
            f"| {r['task'].upper()} | {r['study']} | {override_text or '-'} | {r['group']} | "
            f"{r['n_seeds']} | {r['final_spl_mean']:.2f} ± {r['final_spl_std']:.2f} | "
            f"{r['last5_spl_mean']:.2f} ± {r['last5_spl_std']:.2f} | "
            f"{r['best_spl_mean']:.2f} ± {r['best_spl_std']:.2f} | "
            f"{np.mean(r['mean_spl_over_training']):.2f} | "
            f"{r['runs_reaching_0_7']}/{r['n_seeds']} | "
            f"{'-' if median is None else f'{median:.0f}'} | "
            f"{'-' if hf is None else f'{hf:.2f}'} |"
        )
    (out / "compare.md").write_text("\n".join(lines) + "\n")
    write_json_atomic(out / "compare.json", {"rows": rows}, indent=1)
    for task in sorted({r["task"] for r in rows}):
        groups = sorted(
            (r for r in rows if r["task"] == task), key=lambda r: (r["group"], r["study"])
        )
        fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(groups) + 2), 4.5))
        rng = np.random.default_rng(0)
        for x, row in enumerate(groups):
            values = np.array(row["last5_spl"])
            ax.scatter(x + rng.uniform(-0.15, 0.15, len(values)), values, s=12, alpha=0.6)
            ax.errorbar(x, values.mean(), yerr=values.std(), fmt="D", color="black", capsize=4)
        labels = [f"{r['group']}\n{r['study']}" for r in groups]
        ax.set_xticks(range(len(groups)), labels, rotation=60, fontsize=7)
        ax.set_ylabel("SPL, mean of the last 5 evaluations")
        ax.set_ylim(-0.05, 1.05)
        ax.set_title(f"{task.upper()}: every run (dots), mean ± std per study and method")
        ax.grid(axis="y", alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / f"compare_{task}.png", dpi=110)
        plt.close(fig)
    return rows
