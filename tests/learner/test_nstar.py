"""N*(C) tables from stage-2 rows: useful counts with Wilson intervals, N*, the report."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.learner.nstar import (
    PATH_BITS_ISSUE,
    NStarJob,
    bounds,
    n_star,
    row_key,
    run_jobs,
    success_table,
)
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
        {"method": "bayes_query", "task": "sssg", "feedback": "oracle", "label_channel": "hard",
         "accuracy": 0.6, "decoder_accuracy": None, "n_star": 1000, "above": 2000}
    ]  # fmt: skip
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
        "| bayes_query | SSSG | oracle | hard | 0.6 |  | 250: 1/2 (9%-91%); 500: 2/2 (34%-100%) "
        "| 500 |" in (out / "nstar.md").read_text()
    )


def _subject_rows(channel: str, spls_by_budget: dict[int, list[float]]) -> list[dict]:
    """Rows as a virtual-subject collection writes them (decoder target 0.6)."""
    return [
        {**row, "accuracy": None, "feedback": "virtual_subject", "label_channel": channel,
         "decoder_accuracy": 0.59 + 0.01 * (row["seed"] - 100), "subject_quality": 0.4,
         "decoder_accuracy_target": 0.6}
        for row in _rows(spls_by_budget)
    ]  # fmt: skip


def test_the_table_and_n_star_are_per_feedback_and_channel_and_old_rows_are_the_oracles() -> None:
    old = _rows({1000: [0.0, 0.0, 0.0, 1.0, 1.0]})  # made before other feedback: no fields
    hard = _subject_rows("hard", {1000: [0.0, 0.0, 1.0, 1.0, 1.0]})
    soft = _subject_rows("soft", {1000: [1.0, 1.0, 1.0, 1.0, 0.0]})
    table = success_table(old + hard + soft)
    assert [(r["feedback"], r["label_channel"], r["accuracy"], r["useful"]) for r in table] == [
        ("oracle", "hard", 0.6, 2),
        ("virtual_subject", "hard", 0.6, 3),
        ("virtual_subject", "soft", 0.6, 4),
    ]
    assert table[0]["decoder_accuracy"] is None
    assert table[2]["decoder_accuracy"] == pytest.approx(0.61)  # mean of 0.59..0.63
    stars = {(s["feedback"], s["label_channel"]): s["n_star"] for s in n_star(table)}
    assert stars == {("oracle", "hard"): None, ("virtual_subject", "hard"): None,
                     ("virtual_subject", "soft"): 1000}  # fmt: skip


def test_the_resume_key_tells_channels_and_feedback_apart_and_old_rows_resume(
    tmp_path: Path,
) -> None:
    def job(channel: str) -> NStarJob:
        return NStarJob("sssg", None, 100, "bayes_query", (500,), "virtual_subject", channel, 0.6)

    soft_row = _subject_rows("soft", {500: [1.0]})[0]
    assert row_key(soft_row) == job("soft").key != job("hard").key
    oracle = NStarJob("sssg", 0.6, 100, "bayes_query", (500,))
    assert row_key(_rows({500: [1.0]})[0]) == oracle.key  # an old row, no feedback fields
    assert oracle.key != job("hard").key
    with pytest.raises(ValueError, match="soft label channel"):
        NStarJob("sssg", 0.6, 100, "bayes_query", (500,), "oracle", "soft")
    with pytest.raises(ValueError, match="decoder_accuracy is required"):
        NStarJob("sssg", None, 100, "bayes_query", (500,), "virtual_subject", "soft")
    path = tmp_path / "nstar_rows.json"
    path.write_text(json.dumps([*_rows({500: [1.0]}), soft_row]))
    # both jobs are done: nothing runs (a run would need the subject's factory and fail)
    assert len(run_jobs([oracle, job("soft")], path)) == 2


def test_the_soft_bound_is_the_issues_bits_over_the_measured_bits_per_label() -> None:
    measured = [{"target_accuracy": 0.6, "accuracy": 0.598, "subjects": 5,
                 "hard_bits_bsc": 0.029, "soft_information": 0.042}]  # fmt: skip
    at_06, at_07 = bounds("sssg", [0.6, 0.7], measured)
    assert at_06["soft_30_1"] == pytest.approx(PATH_BITS_ISSUE / 0.042)
    assert at_06["hard_measured_30_1"] == pytest.approx(PATH_BITS_ISSUE / 0.029)
    assert at_06["measured_accuracy"] == 0.598
    assert at_07["soft_30_1"] is None and at_07["hard_30_1"] == pytest.approx(254, abs=1)


def test_report_only_draws_both_channels_and_names_each_series(tmp_path: Path) -> None:
    out = tmp_path / "nstar"
    out.mkdir()
    rows = _subject_rows("hard", {500: [0.0, 1.0]}) + _subject_rows("soft", {500: [1.0, 1.0]})
    (out / "nstar_rows.json").write_text(json.dumps(rows))
    summary = [{"target_accuracy": 0.6, "accuracy": 0.6, "subjects": 2,
                "hard_bits_bsc": 0.029, "soft_information": 0.042}]  # fmt: skip
    (out / "information.json").write_text(json.dumps({"rows": [], "summary": summary}))
    args = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--labels", "500"]
    args += ["--reference-draws", "0", "--report-only", "--feedback", "virtual_subject"]
    args += ["--decoder-accuracy", "0.6", "--label-channel", "soft", "--decoders", "lda"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "bayes_query sssg subject@0.6 hard: N* = > 500" in result.output
    assert "bayes_query sssg subject@0.6 soft: N* = 500" in result.output
    written = json.loads((out / "nstar.json").read_text())
    assert written["bounds"][0]["soft_30_1"] == pytest.approx(PATH_BITS_ISSUE / 0.042)
    table = (out / "nstar.md").read_text()
    assert "| virtual_subject | soft | 0.6 | 0.595 | 500: 2/2 (34%-100%) | 500 |" in table
