"""The confirmatory analysis of docs/protocol.md from the stored rows in this folder.

Reads ``e2e/results.json`` (H1), ``sil_on/results.json`` and ``sil_off/results.json`` (H2),
``nstar/nstar_rows.json`` (H3, H4) and ``information/information.json`` (H5); a missing
file means that hypothesis has not been run. Writes ``analysis.md`` and ``analysis.json``
here and ``docs/figures/confirm_counts.png`` / ``confirm_means.png``. The tests and
intervals are :mod:`services.learner.confirmatory`'s; this script only wires the files.

    python docs/results/confirm/analyse.py
"""

from __future__ import annotations

import json
from pathlib import Path

from services.learner.confirmatory import analyse, markdown_table, plot_estimates, results_json
from services.learner.nstar import load_rows
from services.learner.outputs import load_results

HERE = Path(__file__).resolve().parent
FIGURES = HERE.parents[1] / "figures"


def runs(name: str):
    path = HERE / name / "results.json"
    return load_results(path).runs if path.is_file() else None


def nstar_rows(path: Path):
    return load_rows(path).rows if path.is_file() else None


def information_rows(path: Path):
    return json.loads(path.read_text())["rows"] if path.is_file() else None


def main() -> None:
    results = analyse(
        runs("e2e"),
        runs("sil_on"),
        runs("sil_off"),
        nstar_rows(HERE / "nstar" / "nstar_rows.json"),
        information_rows(HERE / "information" / "information.json"),
    )
    table = markdown_table(results)
    (HERE / "analysis.md").write_text(table)
    (HERE / "analysis.json").write_text(json.dumps(results_json(results), indent=1) + "\n")
    for kind, name in (("count", "confirm_counts.png"), ("mean", "confirm_means.png")):
        plot_estimates(results, kind, FIGURES / name)
    print(table)


if __name__ == "__main__":
    main()
