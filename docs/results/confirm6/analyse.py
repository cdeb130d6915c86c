"""The confirmatory analysis of docs/protocol.md's second family (H6) from the stored rows.

Reads ``anneal/results.json`` (``bgrl reproduce ... --ppo anneal_lr=true``) and
``base/results.json`` (the same command without it), seeds and virtual subjects 4000-4019;
a missing file means that arm has not run. Writes ``analysis.md`` and ``analysis.json``
here and ``docs/figures/confirm6_counts.png`` / ``confirm6_means.png``. The tests,
intervals and Holm adjustment over the family of four are
:func:`services.learner.confirmatory.analyse_h6`'s; this script only wires the files.
Committed before the runs' results were read, as the protocol requires.

    python docs/results/confirm6/analyse.py
"""

from __future__ import annotations

import json
from pathlib import Path

from services.learner.confirmatory import analyse_h6, markdown_table, plot_estimates, results_json
from services.learner.outputs import load_results

HERE = Path(__file__).resolve().parent
FIGURES = HERE.parents[1] / "figures"


def runs(name: str):
    path = HERE / name / "results.json"
    return load_results(path).runs if path.is_file() else None


def main() -> None:
    results = analyse_h6(runs("anneal"), runs("base"))
    table = markdown_table(results)
    (HERE / "analysis.md").write_text(table)
    (HERE / "analysis.json").write_text(json.dumps(results_json(results), indent=1) + "\n")
    for kind, name in (("count", "confirm6_counts.png"), ("mean", "confirm6_means.png")):
        plot_estimates(results, kind, FIGURES / name)
    print(table)


if __name__ == "__main__":
    main()
