"""HF+sparse against RL-sparse with the same PPO settings, pooled over seed sets: runs reaching
SPL 0.7 (Fisher's exact test, one-sided) and mean SPL over training (Mann-Whitney, one-sided).

Usage: python docs/results/sil/stats.py "HF=FOLDER,FOLDER" "RL=FOLDER,FOLDER" [C]
"""

import json
import statistics
import sys
from pathlib import Path

from scipy.stats import fisher_exact, mannwhitneyu


def runs(arg, accuracy):
    label, folders = arg.split("=", 1)
    out = []
    for folder in folders.split(","):
        for run in json.loads((Path(folder) / "results.json").read_text())["runs"]:
            if run["accuracy"] in (None, accuracy):
                out.append(run)
    return label, out


accuracy = float(sys.argv[3]) if len(sys.argv) > 3 else 0.6
(hf_label, hf), (rl_label, rl) = runs(sys.argv[1], accuracy), runs(sys.argv[2], accuracy)
for task in ("sssg", "vssg", "both"):
    a = [r for r in hf if task in ("both", r["task"])]
    b = [r for r in rl if task in ("both", r["task"])]
    ra = sum(r["steps_to_0_7"] is not None for r in a)
    rb = sum(r["steps_to_0_7"] is not None for r in b)
    _, p_reach = fisher_exact([[ra, len(a) - ra], [rb, len(b) - rb]], alternative="greater")
    mean_a = [statistics.fmean(s for _, s in r["curve"]) for r in a]
    mean_b = [statistics.fmean(s for _, s in r["curve"]) for r in b]
    p_mean = mannwhitneyu(mean_a, mean_b, alternative="greater").pvalue
    print(f"{task.upper()}: {hf_label} {ra}/{len(a)} vs {rl_label} {rb}/{len(b)} reach 0.7 "
          f"(Fisher p = {p_reach:.4f}); mean SPL over training {statistics.fmean(mean_a):.2f} vs "
          f"{statistics.fmean(mean_b):.2f} (Mann-Whitney p = {p_mean:.4f})")
