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
from services.learner.outputs import load_results

HERE = Path(__file__).resolve().parent
FIGURES = HERE.parents[1] / "figures"


def runs(name: str):
    path = HERE / name / "results.json"
    return load_results(path).runs if path.is_file() else None


def rows(path: Path, key: str | None = None):
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    return data[key] if key else data


def main() -> None:
    results = analyse(
        runs("e2e"),
        runs("sil_on"),
        runs("sil_off"),
        rows(HERE / "nstar" / "nstar_rows.json"),
        rows(HERE / "information" / "information.json", "rows"),
    )
    table = markdown_table(results)
    (HERE / "analysis.md").write_text(table)
    (HERE / "analysis.json").write_text(json.dumps(results_json(results), indent=1) + "\n")
    for kind, name in (("count", "confirm_counts.png"), ("mean", "confirm_means.png")):
        plot_estimates(results, kind, FIGURES / name)
    print(table)


if __name__ == "__main__":
    main()
