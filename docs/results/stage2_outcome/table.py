"""The screen's table (markdown) from outcome.py's rows: python table.py screen_c06.json"""

import collections
import json
import sys

import numpy as np

rows = json.load(open(sys.argv[1]))["runs"]
cells = collections.defaultdict(list)
for row in rows:
    cells[(row["cell"], row["task"], row["n_labels"])].append(row)
print("| cell (sure:goal:prior) | task | labels | seeds | greedy pi_HF SPL | useful | "
      "sampling success | collisions / goals per run |")
print("|---|---|---|---|---|---|---|---|")
for (cell, task, labels), group in sorted(cells.items()):
    spl = np.array([r["greedy_spl"] for r in group])
    print(f"| {cell} | {task.upper()} | {labels} | {len(group)} | {spl.mean():.2f} ± {spl.std():.2f} "
          f"| {(spl >= 0.5).sum()}/{len(group)} "
          f"| {np.mean([r['sampled_success_rate'] for r in group]):.2f} "
          f"| {np.mean([r['collisions'] for r in group]):.0f} / "
          f"{np.mean([r['goals'] for r in group]):.1f} |")
