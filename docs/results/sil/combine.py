"""Merge the runs of several `bgrl reproduce` folders into one and write its summary and Fig. 3
plots (e.g. HF+sparse and RL-sparse with the same PPO settings, run as separate commands).

Usage: python docs/results/sil/combine.py OUT FOLDER [FOLDER ...]
"""

import sys
from pathlib import Path

from services.learner.outputs import Results, load_results, save_results, write_outputs

out, folders = Path(sys.argv[1]), sys.argv[2:]
parts = [load_results(Path(folder) / "results.json") for folder in folders]
merged = Results(config={"merged_from": folders}, runs=[r for p in parts for r in p.runs])
out.mkdir(parents=True, exist_ok=True)
save_results(out / "results.json", merged)
write_outputs(out, merged.runs)
print((out / "summary.md").read_text())
