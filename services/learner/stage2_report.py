"""The table and plot of a stage-2 sweep (``bgrl hf-sweep``): method x task x C x labels.

Reads the rows of ``hf_policies.json`` (:func:`services.learner.runs.hf_policy_run`) and writes
``summary.md`` (mean ± std of the greedy pi_HF's SPL, runs with a useful pi_HF, i.e. SPL
>= 0.5, sampling pi_HF's success) and ``spl_vs_labels.png`` (greedy SPL against labels, one
line per method and C, one panel per task).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.learner.hf_methods import PAPER_METHOD

USEFUL_SPL = 0.5
"""A pi_HF whose greedy SPL reaches this is counted as useful (issue #12's criterion)."""


def feedback_label(row: dict[str, Any]) -> str:
    """The feedback of a row: the oracle's C (``0.6``), or the virtual subject's target
    decoder accuracy and label channel (``subject@0.6 soft``)."""
    if row.get("feedback", "oracle") == "oracle":
        return f"{row['accuracy']:g}"
    return f"subject@{row['decoder_accuracy_target']:g} {row['label_channel']}"


def group_rows(rows: Sequence[dict[str, Any]]) -> dict[tuple[str, str, str, int], list[dict]]:
    """Rows by (method, task, feedback (:func:`feedback_label`), labels), sorted."""
    groups: dict[tuple[str, str, str, int], list[dict]] = {}
    for row in rows:
        key = (row.get("method", PAPER_METHOD), row["task"], feedback_label(row), row["n_labels"])
        groups.setdefault(key, []).append(row)
    return dict(sorted(groups.items()))


def summary_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table, one line per (method, task, C, labels); for the virtual subject's
    feedback the C column names the target decoder accuracy and the label channel."""
    lines = [
        "| method | task | C | labels | seeds | greedy pi_HF SPL mean ± std | SPL >= 0.5 "
        "| sampling pi_HF success |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for (method, task, accuracy, n_labels), members in group_rows(rows).items():
        greedy = np.array([m["greedy_spl"] for m in members])
        sampled = np.mean([m["sampled_success_rate"] for m in members])
        lines.append(
            f"| {method} | {task.upper()} | {accuracy} | {n_labels} | {len(members)} "
            f"| {greedy.mean():.2f} ± {greedy.std():.2f} "
            f"| {int((greedy >= USEFUL_SPL).sum())}/{len(members)} | {sampled:.2f} |"
        )
    return "\n".join(lines) + "\n"


def plot_spl_vs_labels(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """Greedy pi_HF SPL (mean over seeds) against labels: a panel per task, a line per
    method and C."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_rows(rows)
    tasks = sorted({task for _, task, _, _ in groups})
    fig, axes = plt.subplots(1, len(tasks), figsize=(5.5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        lines: dict[tuple[str, str], list[tuple[int, float]]] = {}
        for (method, t, accuracy, n_labels), members in groups.items():
            if t == task:
                mean = float(np.mean([m["greedy_spl"] for m in members]))
                lines.setdefault((method, accuracy), []).append((n_labels, mean))
        for (method, accuracy), points in sorted(lines.items()):
            xs, ys = zip(*sorted(points), strict=True)
            label = f"C={accuracy}" if accuracy[0].isdigit() else accuracy
            ax.plot(xs, ys, marker="o", label=f"{method} {label}")
        ax.set(title=task.upper(), xlabel="labels", ylabel="greedy pi_HF SPL", ylim=(-0.02, 1))
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(out: Path, rows: Sequence[dict[str, Any]]) -> None:
    """``summary.md`` and ``spl_vs_labels.png`` in ``out``."""
    if not rows:
        return
    (out / "summary.md").write_text(summary_table(rows))
    plot_spl_vs_labels(rows, out / "spl_vs_labels.png")
