"""Per-seed greedy pi_HF SPL of each stage-2 method (docs/stage2.md, "A new method").

Usage: python docs/results/onpolicy_c06/plot.py HF_POLICIES_JSON [HF_POLICIES_JSON ...] OUT_PNG
"""

import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

METHODS = ["paper", "categorical", "categorical_onpolicy"]
rows = [row for path in sys.argv[1:-1] for row in json.load(open(path))["runs"]]
accuracies = sorted({r["accuracy"] for r in rows})
fig, axes = plt.subplots(len(accuracies), 2, figsize=(10, 3.6 * len(accuracies)), squeeze=False)
for i, accuracy in enumerate(accuracies):
    for ax, task in zip(axes[i], ["sssg", "vssg"], strict=True):
        for x, method in enumerate(METHODS):
            spl = np.array(
                [
                    r["greedy_spl"]
                    for r in rows
                    if r["task"] == task and r["method"] == method and r["accuracy"] == accuracy
                ]
            )
            if not len(spl):
                continue
            jitter = np.linspace(-0.15, 0.15, len(spl))
            ax.scatter(x + jitter, spl, s=18, alpha=0.7)
            ax.errorbar(x, spl.mean(), spl.std(), fmt="_", color="k", capsize=8, ms=20)
            ax.text(x, 1.04, f"n={len(spl)}", ha="center", fontsize=8)
        ax.set_xticks(range(len(METHODS)), METHODS, fontsize=8)
        ax.set(title=f"{task.upper()}, C = {accuracy:g}, 1000 labels", ylabel="greedy pi_HF SPL")
        ax.set_ylim(-0.05, 1.1)
        ax.axhline(0.5, color="grey", lw=0.6, ls=":")
fig.tight_layout()
fig.savefig(sys.argv[-1], dpi=110)
