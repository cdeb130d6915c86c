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


def test_an_nstar_folder_holds_one_decoder_set(tmp_path: Path, monkeypatch) -> None:
    """Rows of another --decoders would count in the same series (and their collections be
    skipped as done): refused naming the setting and the folder, nothing written."""
    from services.learner import nstar

    def collect(job: NStarJob, feedback_factory=None) -> list[dict]:
        """A collection's rows without learning (no subject simulated, no decoder trained)."""
        row = _subject_rows(job.label_channel, {job.budgets[0]: [0.0]})[0]
        oracle = job.feedback == "oracle"
        return [{**(_rows({job.budgets[0]: [0.0]})[0] if oracle else row), "seed": job.seed}]

    monkeypatch.setattr(nstar, "nstar_run", collect)
    monkeypatch.setattr(nstar, "ProcessPoolExecutor", _InProcess)
    out = tmp_path / "nstar"
    base = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--labels", "500"]
    base += ["--method", "bayes_query", "--reference-draws", "0"]
    subject = [*base, "--feedback", "virtual_subject", "--decoder-accuracy", "0.6"]
    path = out / "nstar_rows.json"

    result = CliRunner().invoke(app, [*subject, "--seeds", "100-100", "--decoders", "lda"])
    assert result.exit_code == 0, result.output
    recorded = json.loads(path.read_text())["config"]["feedback_source"]
    assert recorded["decoders"] == ["lda"] and "max_passes" in recorded
    before = path.read_text()
    refused = CliRunner().invoke(app, [*subject, "--seeds", "100-101"])  # the default decoders
    assert refused.exit_code == 2, refused.output
    message = _flat(refused.output)
    assert _flat("decoders ['lda'], not ['eegnet', 'lda', 'xdawn_rg']") in message
    assert _flat(f"{out} holds virtual-subject runs") in message
    assert path.read_text() == before
    # collections of the oracle's feedback need no decoders and keep the folder's record
    result = CliRunner().invoke(app, [*base, "--seeds", "100-100", "--accuracies", "0.6"])
    assert result.exit_code == 0, result.output
    assert nstar.load_rows(path).feedback_source == recorded
    assert len(nstar.load_rows(path).rows) == 2
    # a list of rows, as written before the record: its subjects had the default decoders
    path.write_text(json.dumps(nstar.load_rows(path).rows))
    assert nstar.load_rows(path).feedback_source is None
    refused = CliRunner().invoke(app, [*subject, "--seeds", "100-101", "--decoders", "lda"])
    assert refused.exit_code == 2
    assert _flat("decoders ['eegnet', 'lda', 'xdawn_rg'], not ['lda']") in _flat(refused.output)
    result = CliRunner().invoke(app, [*subject, "--seeds", "100-101"])
    assert result.exit_code == 0, result.output
    assert nstar.load_rows(path).feedback_source["decoders"] == ["eegnet", "lda", "xdawn_rg"]
    assert len(nstar.load_rows(path).rows) == 3


def test_include_refuses_a_sweep_of_another_decoder_set(tmp_path: Path) -> None:
    """A sweep's virtual-subject rows made with other decoders would join the table's series."""
    out, sweep = tmp_path / "nstar", tmp_path / "sweep"
    out.mkdir()
    sweep.mkdir()
    lda = {"decoders": ["lda"], "max_passes": 300}
    rows = _subject_rows("hard", {500: [1.0]})
    (out / "nstar_rows.json").write_text(
        json.dumps({"config": {"feedback_source": lda}, "rows": rows})
    )
    theirs = [{**row, "sampled_success_rate": 1.0} for row in _subject_rows("hard", {1000: [1.0]})]
    document = {"runs": theirs, "failed": []}  # written before the record: the default set
    (sweep / "hf_policies.json").write_text(json.dumps(document))
    args = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--labels", "500,1000"]
    args += [
        "--reference-draws",
        "0",
        "--report-only",
        "--include",
        str(sweep / "hf_policies.json"),
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    message = _flat(result.output)
    assert _flat("'decoders': ['eegnet', 'lda', 'xdawn_rg']") in message
    assert _flat("a table holds one decoder set") in message
    assert not (out / "nstar.json").exists()
    # the same set recorded: included
    (sweep / "hf_policies.json").write_text(
        json.dumps({"config": {"feedback_source": lda}, **document})
    )
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert len(json.loads((out / "nstar.json").read_text())["table"]) == 2


def test_a_rows_file_that_is_not_one_is_a_one_line_error_and_left_alone(tmp_path: Path) -> None:
    out = tmp_path / "nstar"
    out.mkdir()
    content = '{"rows": 3}'
    (out / "nstar_rows.json").write_text(content)
    for extra in ([], ["--report-only"]):
        args = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--labels", "500", *extra]
        result = CliRunner().invoke(app, [*args, "--reference-draws", "0"])
        assert result.exit_code == 2, result.output
        assert _flat("not a `bgrl hf-nstar` rows file") in _flat(result.output)
        assert (out / "nstar_rows.json").read_text() == content


class _InProcess:
    """``ProcessPoolExecutor`` without the spawned workers."""

    def __init__(self, max_workers: int) -> None:
        pass

    def __enter__(self) -> _InProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def map(self, function, items):
        return map(function, items)


def _flat(text: str) -> str:
    """``text`` without spaces and box borders (the CLI's error box wraps its lines)."""
    return "".join(text.replace("│", "").split())


def test_an_interrupted_nstar_counts_the_rows_kept(tmp_path: Path, monkeypatch) -> None:
    """The rows file is a document beside its settings block: the rows are counted, not
    its keys."""
    from services.learner import nstar

    def collect(job: NStarJob, feedback_factory=None) -> list[dict]:
        if job.seed == 101:
            raise KeyboardInterrupt
        return [{**row, "seed": job.seed} for row in _rows({n: [0.0] for n in job.budgets})]

    monkeypatch.setattr(nstar, "nstar_run", collect)
    monkeypatch.setattr(nstar, "ProcessPoolExecutor", _InProcess)
    out = tmp_path / "nstar"
    args = ["hf-nstar", "--out", str(out), "--tasks", "sssg", "--labels", "250,500,1000"]
    result = CliRunner().invoke(app, [*args, "--accuracies", "0.6", "--seeds", "100-101"])
    assert result.exit_code == 130, result.output
    kept = f"3 row(s) (a run at a budget each) kept in {out / 'nstar_rows.json'}"
    assert _flat(kept) in _flat(result.output)
