"""N*(C) tables from stage-2 rows: useful counts with Wilson intervals, N*, the report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.learner.nstar import n_star, success_table
from services.learner.stats import wilson_interval


def _rows(spls_by_budget: dict[int, list[float]], c: float = 0.6) -> list[dict]:
    return [
        {
            "task": "sssg",
            "accuracy": c,
            "seed": 100 + i,
            "method": "bayes_query",
            "n_labels": n,
            "greedy_spl": spl,
        }
        for n, spls in spls_by_budget.items()
        for i, spl in enumerate(spls)
    ]


def test_success_table_counts_useful_runs_and_n_star_is_the_first_budget_at_80_percent() -> None:
    rows = _rows({500: [0.0, 0.6, 0.0, 0.0, 0.9], 1000: [0.5, 0.6, 0.0, 1.0, 0.9], 2000: [1.0] * 5})
    table = success_table(rows)
    assert [(r["n_labels"], r["useful"], r["runs"]) for r in table] == [
        (500, 2, 5),
        (1000, 4, 5),
        (2000, 5, 5),
    ]
    assert (table[0]["wilson_low"], table[0]["wilson_high"]) == pytest.approx(wilson_interval(2, 5))
    assert n_star(table) == [
        {"method": "bayes_query", "task": "sssg", "accuracy": 0.6, "n_star": 1000, "above": 2000}
    ]
    assert n_star(success_table(_rows({500: [0.0] * 5})))[0]["n_star"] is None


def test_report_only_writes_table_figure_and_n_star_from_stored_rows(tmp_path: Path) -> None:
    """No run is made: the rows in OUT and the cached reference make the outputs."""
    out = tmp_path / "nstar"
    out.mkdir()
    (out / "nstar_rows.json").write_text(json.dumps(_rows({250: [0.0, 1.0], 500: [1.0, 1.0]})))
    grid = [100, 200, 250, 300, 400, 500]
    reference = [
        {"task": "sssg", "accuracy": 0.6, "rule": rule, "draws": 10,
         "identified": {str(n): n / 500 for n in grid}, "n_star": 400}
        for rule in ("round_robin", "adaptive", "adaptive_forward")
    ]  # fmt: skip
    params = {"path": "sssg", "accuracies": [0.6], "grid": grid, "draws": 10}
    (out / "reference.json").write_text(json.dumps({"params": params, "reference": reference}))
    args = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--accuracies", "0.6"]
    args += ["--labels", "250,500", "--reference-draws", "10", "--report-only"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "bayes_query sssg C=0.6: N* = 500" in result.output
    written = json.loads((out / "nstar.json").read_text())
    assert written["n_star"][0]["n_star"] == 500 and written["bounds"][0]["hard_30_1"] > 1000
    assert (out / "nstar.png").stat().st_size > 0 and (out / "nstar.csv").exists()
    assert (
        "| bayes_query | SSSG | 0.6 | 250: 1/2 (9%-91%); 500: 2/2 (34%-100%) | 500 |"
        in (out / "nstar.md").read_text()
    )
