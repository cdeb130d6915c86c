"""Table of docs/stage2.md's smoothness-prior section: categorical_kernel against the
10-seed rows of categorical and paper, paired by seed (Wilcoxon signed-rank).

Usage (from the repository root):
    python docs/results/stage2_kernel/compare.py docs/results/stage2_kernel/hf_policies.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import wilcoxon

ROOT = Path(__file__).resolve().parents[3]
BASELINE = ROOT / "docs/results/stage2_10seeds/hf_policies.json"
REPRODUCTION = ROOT / "docs/results/reproduce_seedseq/results.json"
USEFUL = 0.5


def rows(path: Path) -> dict[tuple, dict]:
    """(method, task, C, labels, seed) -> row."""
    data = json.loads(path.read_text())["runs"]
    return {(r["method"], r["task"], r["accuracy"], r["n_labels"], r["seed"]): r for r in data}


def paper_1000() -> dict[tuple, dict]:
    """The paper's Fhat at 1000 labels: the reproduction's greedy pi_HF SPL per seed."""
    out = {}
    for r in json.loads(REPRODUCTION.read_text())["runs"]:
        if r["method"] == "hf_sparse" and r["hf_policy_spl"] is not None:
            key = ("paper", r["task"], r["accuracy"], 1000, r["seed"])
            out[key] = {"greedy_spl": r["hf_policy_spl"], "sampled_success_rate": None}
    return out


def main(new_path: str) -> None:
    new = {k: r for k, r in rows(Path(new_path)).items() if k[0] == "categorical_kernel"}
    known = {**rows(BASELINE), **paper_1000(), **rows(Path(new_path))}
    cells = sorted({k[1:4] for k in new}, key=lambda c: (-c[1], -c[2], c[0]))
    print(
        "| method | task | C | labels | seeds | greedy pi_HF SPL mean ± std | useful "
        "(SPL >= 0.5) | sampling pi_HF success | vs categorical, paired: wins/ties/losses, "
        "Wilcoxon p (two-sided) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for task, c, n in cells:
        seeds = sorted(k[4] for k in new if k[1:4] == (task, c, n))
        for method in ("paper", "categorical", "categorical_kernel"):
            got = [known.get((method, task, c, n, s)) for s in seeds]
            if any(g is None for g in got):
                continue
            spl = np.array([g["greedy_spl"] for g in got])
            sampled = [g["sampled_success_rate"] for g in got]
            sampled_text = "-" if None in sampled else f"{np.mean(sampled):.2f}"
            paired = "-"
            if method == "categorical_kernel":
                base = np.array(
                    [known[("categorical", task, c, n, s)]["greedy_spl"] for s in seeds]
                )
                diff = spl - base
                wins, ties, losses = (diff > 0).sum(), (diff == 0).sum(), (diff < 0).sum()
                p = wilcoxon(spl, base).pvalue if np.any(diff != 0) else 1.0
                paired = f"{wins}/{ties}/{losses}, p = {p:.2f}"
            print(
                f"| {method} | {task.upper()} | {c:g} | {n} | {len(seeds)} | "
                f"{spl.mean():.2f} ± {spl.std():.2f} | {(spl >= USEFUL).sum()}/{len(seeds)} | "
                f"{sampled_text} | {paired} |"
            )
    print()
    print("Both tasks pooled, paired by (task, seed): categorical_kernel against ...")
    for c, n in sorted({k[2:4] for k in new}, key=lambda cell: (-cell[0], -cell[1])):
        pairs = [k for k in new if k[2:4] == (c, n)]
        ker = np.array([new[k]["greedy_spl"] for k in pairs])
        for base in ("categorical", "paper"):
            keys = [(base, *k[1:]) for k in pairs]
            if any(k not in known for k in keys):
                continue
            other = np.array([known[k]["greedy_spl"] for k in keys])
            diff = ker - other
            p = wilcoxon(ker, other).pvalue if np.any(diff != 0) else 1.0
            print(
                f"- C={c:g} {n} labels vs {base}: useful {(ker >= USEFUL).sum()}/{len(ker)} "
                f"vs {(other >= USEFUL).sum()}/{len(ker)}, wins/ties/losses "
                f"{(diff > 0).sum()}/{(diff == 0).sum()}/{(diff < 0).sum()}, "
                f"Wilcoxon p = {p:.3f} (two-sided)"
            )
    print()
    print("Per seed, greedy SPL (categorical_kernel / categorical):")
    for task, c, n in cells:
        seeds = sorted(k[4] for k in new if k[1:4] == (task, c, n))
        ker = " ".join(
            f"{new[('categorical_kernel', task, c, n, s)]['greedy_spl']:.2g}" for s in seeds
        )
        cat = " ".join(
            f"{known[('categorical', task, c, n, s)]['greedy_spl']:.2g}"
            if ("categorical", task, c, n, s) in known
            else "?"
            for s in seeds
        )
        print(f"- {task.upper()} C={c:g} {n}: {ker} / {cat}")


if __name__ == "__main__":
    main(sys.argv[1])
