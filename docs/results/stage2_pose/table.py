"""Per (C, method, settings, task): mean greedy pi_HF SPL, useful runs (>= 0.5), sampling success.

Usage: python docs/results/stage2_pose/table.py tune_c06.json [more.json ...]
"""

import json
import sys
from collections import defaultdict

import numpy as np

cells = defaultdict(list)
for path in sys.argv[1:]:
    for row in json.load(open(path))["runs"]:
        settings = ",".join(f"{k.replace('kernel_', '')}={v}" for k, v in sorted(row["settings"].items()))
        cells[(row["accuracy"], row["method"], settings, row["task"])].append(row)
print("| C | method | settings | task | seeds | greedy SPL mean ± std | useful | sampling success |")
print("|---|---|---|---|---|---|---|---|")
for (c, method, settings, task), rows in sorted(cells.items()):
    spl = np.array([r["greedy_spl"] for r in rows])
    success = np.mean([r["sampled_success_rate"] for r in rows])
    print(f"| {c} | {method} | {settings or '-'} | {task} | {len(rows)} | {spl.mean():.2f} ± {spl.std():.2f} "
          f"| {(spl >= 0.5).sum()}/{len(rows)} | {success:.2f} |")
