"""The issue-#12 stage-3 figures of `bgrl reproduce` folders: per (folder, task, method, C),
runs reaching SPL 0.7 within the budget, last-five-evaluation and final SPL, best SPL and
collapses (an evaluation >= 0.7 followed by one < 0.3).

Usage: python docs/results/sil/table.py LABEL=FOLDER [LABEL=FOLDER ...]
"""

import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path


def collapses(spls):
    return sum(1 for a, b in zip(spls, spls[1:]) if a >= 0.7 and b < 0.3)


def fmt(values):
    mean = statistics.fmean(values)
    std = statistics.pstdev(values)
    return f"{mean:.2f} ± {std:.2f}"


print("| study | task | method | seeds | runs reaching 0.7 | median steps to 0.7 | last-5 SPL | "
      "final SPL | best SPL | collapses |")
print("|---|---|---|---|---|---|---|---|---|---|")
for arg in sys.argv[1:]:
    label, folder = arg.split("=", 1)
    cells = defaultdict(list)
    for run in json.loads((Path(folder) / "results.json").read_text())["runs"]:
        name = run["method"] if run["accuracy"] is None else f"{run['method']} C={run['accuracy']}"
        cells[(run["task"], name)].append(run)
    for (task, name), runs in sorted(cells.items()):
        spls = [[spl for _, spl in r["curve"]] for r in runs]
        steps = sorted(r["steps_to_0_7"] for r in runs if r["steps_to_0_7"] is not None)
        median = f"{statistics.median(steps):.0f}" if steps else "-"
        print(f"| {label} | {task.upper()} | {name} | {len(runs)} | {len(steps)}/{len(runs)} | "
              f"{median} | {fmt([statistics.fmean(s[-5:]) for s in spls])} | "
              f"{fmt([r['final_spl'] for r in runs])} | {fmt([max(s) for s in spls])} | "
              f"{sum(collapses(s) for s in spls)} |")
