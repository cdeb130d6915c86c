"""The `bgrl` research commands as a script uses them and as other tools read their files:
bad arguments are one-line errors that leave ``--out`` alone, Ctrl-C stops at once and
keeps a consistent, resumable folder, JSON is strict, CSVs have a header, plots are PNGs."""

from __future__ import annotations

import csv
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.learner import pool
from services.learner.runs import RunFailure, RunRecord
from services.learner.specs import RunSpec

REPO = Path(__file__).resolve().parents[2]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _strict_json(path: Path) -> Any:
    """``path`` parsed as strict JSON (NaN / Infinity tokens raise)."""

    def refuse(token: str) -> None:
        raise ValueError(f"{path.name}: non-JSON constant {token}")

    return json.loads(path.read_text(), parse_constant=refuse)


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        reader = csv.DictReader(handle)
        assert reader.fieldnames, f"{path.name} has no header"
        return list(reader)


def _one_line_error(result: Any, *needles: str) -> None:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    flat = "".join(result.output.replace("│", "").split())  # the error box wraps lines
    for needle in needles:
        assert "".join(needle.split()) in flat, result.output


def _no_runs(*args: Any, **kwargs: Any) -> None:
    raise AssertionError("bad input must be refused before any run starts")


def _record(spec: RunSpec) -> RunRecord:
    """A finished run's record without training (what ``run_one`` returns)."""
    curve = [[0, 0.0], [1024, 0.5], [2048, 1.0]]
    return RunRecord(
        task=spec.task, method=spec.method, accuracy=spec.accuracy, seed=spec.seed,
        hf_treatment=spec.hf_treatment, curve=curve, final_spl=1.0, hf_policy_spl=None,
        wall_seconds=0.1, steps_to_0_7=2048, spec=spec.to_dict(), best_step=2048, best_spl=1.0,
    )  # fmt: skip


# ------------------------------------------------------------------ bad arguments


REPRODUCE = ["reproduce", "--seeds", "1", "--tasks", "sssg", "--methods", "rl_sparse"]


@pytest.mark.parametrize(
    ("extra", "needles"),
    [
        (["--tasks", "sssg,sssg"], ["--tasks", "sssg repeated"]),
        (["--methods", ""], ["--methods", "at least one"]),
        (["--methods", "hf_sparse", "--accuracies", "0.7,0.70"], ["--accuracies", "0.7 repeated"]),
        (["--methods", "hf_sparse", "--accuracies", "nan"], ["--accuracies", "'nan' is not in"]),
        (["--methods", "hf_sparse", "--accuracies", "1.5"], ["--accuracies", "not in [0, 1]"]),
        (["--treatments", "authors,authors"], ["--treatments", "authors repeated"]),
        (["--ppo", "minibatch_size=0"], ["--ppo minibatch_size must be in [1, inf), not 0"]),
        (["--ppo", "n_epochs=-1"], ["--ppo n_epochs must be in [1, inf), not -1"]),
        (["--ppo", "learning_rate=nan"], ["--ppo learning_rate must be in (0, inf), not nan"]),
        (["--ppo", "gamma=inf"], ["--ppo gamma must be in [0, 1], not inf"]),
        (["--ppo", "hidden_sizes=64,0"], ["--ppo every entry of hidden_sizes", "[1, inf), not 0"]),
        # a factor study must not silently take the last of two values of one setting
        (["--ppo", "n_epochs=10", "--ppo", "n_epochs=2"], ["--ppo n_epochs given twice"]),
        (["--first-seed", str(2**31)], ["--first-seed"]),
        (["--seeds", "2", "--first-seed", str(2**31 - 1)], ["--first-seed", "2147483648"]),
    ],
)
def test_reproduce_refuses_bad_arguments_in_one_line_before_touching_out(
    tmp_path, monkeypatch, extra, needles
) -> None:
    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    out = tmp_path / "study"
    result = CliRunner().invoke(app, [*REPRODUCE, "--out", str(out), *extra])
    _one_line_error(result, *needles)
    assert not out.exists()


@pytest.mark.parametrize(
    ("extra", "needles"),
    [
        (["--labels", "20,20"], ["--labels", "20 repeated"]),
        (["--accuracies", "0.7,0.7"], ["--accuracies", "0.7 repeated"]),
        (["--tasks", ""], ["--tasks", "at least one"]),
        (["--tasks", "sssg,nope"], ["--tasks", "unknown task 'nope'"]),
        (["--method", "paper,paper"], ["--method", "paper repeated"]),
    ],
)
def test_hf_sweep_refuses_bad_arguments_in_one_line_before_touching_out(
    tmp_path, monkeypatch, extra, needles
) -> None:
    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    out = tmp_path / "sweep"
    args = ["hf-sweep", "--out", str(out), "--seeds", "1", "--tasks", "sssg", "--labels", "20"]
    result = CliRunner().invoke(app, [*args, "--accuracies", "0.7", *extra])
    _one_line_error(result, *needles)
    assert not out.exists()


def test_ppo_overrides_are_parsed_and_checked_by_the_learners_rules() -> None:
    from services.cli.learner import parse_ppo_overrides

    assert parse_ppo_overrides(["target_kl=none", "gamma=1", "hidden_sizes=32,32"]) == {
        "target_kl": None, "gamma": 1.0, "hidden_sizes": (32, 32),
    }  # fmt: skip
    with pytest.raises(ValueError, match=r"--ppo hf_t_trans_fraction must be in \(0, 1\], not 0"):
        parse_ppo_overrides(["hf_t_trans_fraction=0"])


def _bench_never_runs(*args: Any, **kwargs: Any) -> None:
    raise AssertionError("the output folder must be checked before the benchmark runs")


@pytest.mark.parametrize(
    "command",
    [
        [*REPRODUCE, "--out", "{file}"],
        ["hf-sweep", "--seeds", "1", "--tasks", "sssg", "--labels", "5", "--out", "{file}"],
        ["reproduce", "--seeds", "1", "--tasks", "sssg", "--out", "{file}/below"],
        ["compare", "{study}", "--out", "{file}"],
        ["compare", "{study}", "--out", "{file}/below"],
        ["sim", "map-png", "--out", "{file}/map.png"],
        ["sim", "map-png", "--out", "{dir}/map.txt"],
        ["sim", "random-success", "--episodes", "1", "--out", "{dir}"],
        ["subject", "simulate", "--actions", "5", "--out", "{file}/s.bdf"],
        ["eeg", "calibrate", "{dir}/none.bdf", "--out", "{file}"],
        ["eeg", "quality-sweep", "--seeds", "1", "--actions", "60", "--out", "{file}"],
        ["bench", "learner", "--out", "{file}"],
        ["bench", "sweep", "--out", "{file}"],
        ["bench", "sim", "--out", "{file}"],
        ["bench", "eeg", "--memory-only", "--out", "{file}"],
    ],
)
def test_an_out_that_cannot_be_written_is_a_one_line_error_and_no_work(
    tmp_path, monkeypatch, command
) -> None:
    import benchmarks.bench_eeg
    import benchmarks.bench_learner
    import benchmarks.bench_sim
    import benchmarks.bench_sweep

    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    monkeypatch.setattr(benchmarks.bench_sweep, "run", _bench_never_runs)
    monkeypatch.setattr(benchmarks.bench_learner, "run_benchmark", _bench_never_runs)
    monkeypatch.setattr(benchmarks.bench_sim, "run", _bench_never_runs)
    monkeypatch.setattr(benchmarks.bench_eeg, "bench_memory", _bench_never_runs)
    monkeypatch.setattr(benchmarks.bench_eeg, "quality_sweep", _bench_never_runs)
    study = tmp_path / "study"
    study.mkdir()
    spec = RunSpec("sssg", "rl_sparse", 0)
    pool.save_results(study / "results.json", pool.Results(config={}, runs=[_record(spec)]))
    file = tmp_path / "results.txt"
    file.write_text("keep me\n")
    names = {"file": str(file), "dir": str(tmp_path), "study": str(study)}
    result = CliRunner().invoke(app, [part.format(**names) for part in command])
    _one_line_error(result, "--out")
    assert file.read_text() == "keep me\n"


@pytest.mark.parametrize("seed_command", [["sim", "random-success"], ["subject", "simulate"]])
def test_a_negative_seed_is_refused_by_the_option(tmp_path, seed_command) -> None:
    args = [*seed_command, "--seed", "-1", "--out", str(tmp_path / "x.bdf")]
    _one_line_error(CliRunner().invoke(app, args), "--seed")


@pytest.mark.parametrize(
    "content", ["[]", '{"runs": [{"task": "sssg"}]}', "not json", '{"runs": [], "failed": [1]}']
)
def test_hf_sweep_into_a_folder_with_a_foreign_hf_policies_json_leaves_it_alone(
    tmp_path, monkeypatch, content
) -> None:
    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    (tmp_path / "hf_policies.json").write_text(content)
    args = ["hf-sweep", "--out", str(tmp_path), "--seeds", "1", "--tasks", "sssg", "--labels", "5"]
    result = CliRunner().invoke(app, args)
    _one_line_error(result, "--out", "hf_policies.json", "not a `bgrl hf-sweep` results file")
    assert (tmp_path / "hf_policies.json").read_text() == content


@pytest.mark.parametrize(
    ("command", "others"),
    [
        (["hf-sweep", "--seeds", "1", "--tasks", "sssg", "--labels", "5"], "results.json"),
        (REPRODUCE, "hf_policies.json"),
    ],
)
def test_reproduce_and_hf_sweep_keep_out_of_each_others_folder(
    tmp_path, monkeypatch, command, others
) -> None:
    """Both write summary.md: one would overwrite the other's."""
    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    (tmp_path / others).write_text('{"runs": []}')
    (tmp_path / "summary.md").write_text("the other study's summary")
    result = CliRunner().invoke(app, [*command, "--out", str(tmp_path)])
    _one_line_error(result, "--out", "holds a", others, "a folder of its own")
    assert (tmp_path / "summary.md").read_text() == "the other study's summary"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([others, "summary.md"])


def test_hf_sweep_keeps_earlier_failures_of_runs_it_does_not_retry(tmp_path, monkeypatch) -> None:
    def fail_all(function, batches, *, workers, on_result, on_failure) -> None:
        for batch in batches:  # e.g. the batch's worker died: each of its runs failed
            on_failure(RunFailure.from_exception(batch, RuntimeError("boom")))

    def succeed(function, batches, *, workers, on_result, on_failure) -> None:
        for batch in batches:
            on_result([
                {"task": spec.task, "accuracy": spec.accuracy, "seed": spec.seed,
                 "n_labels": spec.n_labels, "method": spec.method, "greedy_spl": 1.0,
                 "sampled_success_rate": 1.0}
                for spec in batch.specs
            ])  # fmt: skip

    base = ["hf-sweep", "--out", str(tmp_path), "--seeds", "1", "--labels", "5"]
    monkeypatch.setattr(pool, "run_isolated", fail_all)
    assert CliRunner().invoke(app, [*base, "--tasks", "sssg,vssg"]).exit_code == 1
    monkeypatch.setattr(pool, "run_isolated", succeed)
    result = CliRunner().invoke(app, [*base, "--tasks", "sssg"])
    assert result.exit_code == 1, result.output  # the vssg runs still stand failed
    document = _strict_json(tmp_path / "hf_policies.json")
    assert {r["task"] for r in document["runs"]} == {"sssg"}
    assert {f["spec"]["task"] for f in document["failed"]} == {"vssg"}


def _study(folder: Path, seeds: list[int]) -> Path:
    """A `bgrl reproduce` folder of RL-sparse runs of ``seeds`` (records made up)."""
    from services.learner.outputs import Results, save_results

    folder.mkdir(parents=True)
    records = [_record(RunSpec("sssg", "rl_sparse", seed)) for seed in seeds]
    save_results(folder / "results.json", Results(config={}, runs=records))
    return folder


def test_compare_tells_studies_of_one_folder_name_apart(tmp_path) -> None:
    """Two `.../study` folders (e.g. two dates' runs of one command) are two rows a reader
    can tell apart, named by as much of their paths as it takes."""
    first = _study(tmp_path / "jan" / "study", [0, 1])
    second = _study(tmp_path / "feb" / "study", [0, 1, 2])
    out = tmp_path / "compare"
    result = CliRunner().invoke(app, ["compare", str(first), str(second), "--out", str(out)])
    assert result.exit_code == 0, result.output
    rows = _strict_json(out / "compare.json")["rows"]
    assert sorted((r["study"], r["n_seeds"]) for r in rows) == [("feb/study", 3), ("jan/study", 2)]
    assert "| jan/study |" in (out / "compare.md").read_text()


def test_a_results_json_that_is_a_folder_is_named_as_such(tmp_path, monkeypatch) -> None:
    """Not reported as missing ("no results.json") when it is there, as a folder."""
    monkeypatch.setattr(pool, "run_isolated", _no_runs)
    (tmp_path / "study" / "results.json").mkdir(parents=True)
    where = tmp_path / "study" / "results.json"
    result = CliRunner().invoke(app, [*REPRODUCE, "--out", str(tmp_path / "study")])
    _one_line_error(result, f"{where}: a folder, not a results file")
    result = CliRunner().invoke(
        app, ["compare", str(tmp_path / "study"), "--out", str(tmp_path / "c")]
    )
    _one_line_error(result, f"{where}: a folder, not a results file")


def test_compare_refuses_one_study_given_twice(tmp_path) -> None:
    """Its runs would count twice, as if they were another study's."""
    study = _study(tmp_path / "study", [0])
    out = tmp_path / "compare"
    args = ["compare", str(study), str(tmp_path / "." / "study"), "--out", str(out)]
    _one_line_error(CliRunner().invoke(app, args), "given twice")
    assert not out.exists()


# ------------------------------------------------------------------ interruption


def test_interrupting_run_isolated_drops_queued_runs_and_ends_its_workers() -> None:
    interrupted_at: list[float] = []
    before = set(multiprocessing.active_children())

    def interrupt(_: Any) -> None:  # as Ctrl-C arriving while the parent waits
        interrupted_at.append(time.monotonic())
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        pool.run_isolated(
            time.sleep, [0.0, 3.0, 3.0, 3.0, 3.0], workers=1,
            on_result=interrupt, on_failure=lambda failure: None,
        )  # fmt: skip
    assert time.monotonic() - interrupted_at[0] < 2.0  # not the 12 s of queued runs
    left = [(c.name, c.pid, c.exitcode) for c in set(multiprocessing.active_children()) - before]
    assert left == []


def test_reproduce_interrupted_keeps_a_consistent_folder_and_resumes(tmp_path, monkeypatch) -> None:
    def one_then_ctrl_c(function, specs, *, workers, on_result, on_failure) -> None:
        on_result(_record(specs[0]))
        raise KeyboardInterrupt

    args = [*REPRODUCE, "--seeds", "3", "--out", str(tmp_path), "--single-run"]
    monkeypatch.setattr(pool, "run_isolated", one_then_ctrl_c)
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 130, result.output
    assert "interrupted" in result.output and "run the same command again" in result.output
    assert f"1 finished run(s) kept in {tmp_path / 'results.json'}" in result.output
    assert len(_strict_json(tmp_path / "results.json")["runs"]) == 1
    assert [r["seed"] for r in _csv_rows(tmp_path / "results.csv")] == ["0"]  # up to date
    assert _strict_json(tmp_path / "summary.json")["groups"][0]["n_seeds"] == 1
    assert (tmp_path / "fig3_sssg.png").read_bytes().startswith(PNG_SIGNATURE)

    resumed: list[int] = []

    def the_rest(function, specs, *, workers, on_result, on_failure) -> None:
        for spec in specs:
            resumed.append(spec.seed)
            on_result(_record(spec))

    monkeypatch.setattr(pool, "run_isolated", the_rest)
    assert CliRunner().invoke(app, args).exit_code == 0
    assert resumed == [1, 2]
    rows = _csv_rows(tmp_path / "results.csv")
    assert [r["seed"] for r in rows] == ["0", "1", "2"] and rows[0]["curve"].startswith("0:")


def test_an_interrupted_lockstep_reproduction_keeps_the_batches_done(tmp_path, monkeypatch) -> None:
    def one_batch_then_ctrl_c(function, batches, *, workers, on_result, on_failure) -> None:
        on_result([_record(spec) for spec in batches[0].specs])
        raise KeyboardInterrupt

    args = [*REPRODUCE, "--seeds", "3", "--out", str(tmp_path), "--workers", "2"]
    monkeypatch.setattr(pool, "run_isolated", one_batch_then_ctrl_c)
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 130, result.output
    # two batches for two workers, the seeds dealt round-robin: [0, 2] and [1]
    assert [r["seed"] for r in _csv_rows(tmp_path / "results.csv")] == ["0", "2"]
    resumed: list[int] = []

    def the_rest(function, batches, *, workers, on_result, on_failure) -> None:
        for batch in batches:
            resumed.extend(spec.seed for spec in batch.specs)
            on_result([_record(spec) for spec in batch.specs])

    monkeypatch.setattr(pool, "run_isolated", the_rest)
    assert CliRunner().invoke(app, args).exit_code == 0
    assert resumed == [1]
    assert [r["seed"] for r in _csv_rows(tmp_path / "results.csv")] == ["0", "1", "2"]


def test_a_lockstep_reproduction_interrupted_before_any_run_finished_says_so(
    tmp_path, monkeypatch
) -> None:
    """Not that finished runs are kept in a results.json that does not exist: the
    checkpoints of the unfinished runs are what is kept."""

    def checkpoints_then_ctrl_c(function, batches, *, workers, on_result, on_failure) -> None:
        for spec in batches[0].specs:  # what a batch wrote before Ctrl-C
            pool.checkpoint_path(batches[0].checkpoint_dir, spec).write_bytes(b"state")
        raise KeyboardInterrupt

    args = [*REPRODUCE, "--seeds", "3", "--out", str(tmp_path), "--workers", "2"]
    monkeypatch.setattr(pool, "run_isolated", checkpoints_then_ctrl_c)
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 130, result.output
    assert "finished runs are kept" not in result.output
    assert "no run finished" in result.output
    assert f"2 unfinished run(s) keep their checkpoints in {tmp_path / 'checkpoints'}" in (
        result.output
    )
    assert not (tmp_path / "results.json").exists()


def _sigint_as_a_terminal() -> None:
    """The child's SIGINT as a terminal gives it: default. A test run started as a background
    job of a shell without job control inherits SIGINT ignored, and a Python started so keeps
    ignoring it (it installs KeyboardInterrupt only over the default)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_stops_a_real_hf_sweep_at_once_and_a_rerun_resumes(tmp_path) -> None:
    out = tmp_path / "sweep"
    command = [  # runs alone: a lockstep batch hands its rows over when it ends
        sys.executable, "-m", "services.cli.main", "hf-sweep", "--out", str(out),
        "--tasks", "sssg", "--accuracies", "0.7", "--labels", "100", "--workers", "1",
        "--single-run",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        [*command, "--seeds", "30"], cwd=REPO, env=env, start_new_session=True,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, preexec_fn=_sigint_as_a_terminal,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240  # ~10 s idle; a loaded machine is far slower
        while not (out / "hf_policies.json").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert (out / "hf_policies.json").exists(), "no run finished in 240 s"
        os.killpg(process.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        sent = time.monotonic()
        output = process.communicate(timeout=90)[0].decode()  # bounded below
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    # the run in hand may finish (~10 s idle, 18 s seen in a full suite run); the 28 queued
    # ones (~5 min) must not start
    assert time.monotonic() - sent < 60, "still running the queued runs after Ctrl-C"
    assert process.returncode == 130, output
    assert "Traceback" not in output and "interrupted" in output
    rows = _strict_json(out / "hf_policies.json")["runs"]
    assert 1 <= len(rows) < 30
    assert f"| paper | SSSG | 0.7 | 100 | {len(rows)} |" in (out / "summary.md").read_text()
    assert (out / "spl_vs_labels.png").read_bytes().startswith(PNG_SIGNATURE)
    rerun = subprocess.run(
        [*command, "--seeds", "1"], cwd=REPO, env=env, capture_output=True, timeout=60
    )
    assert rerun.returncode == 0, rerun.stdout.decode() + rerun.stderr.decode()
    assert _strict_json(out / "hf_policies.json")["runs"] == rows  # seed 0 is not run again


# ------------------------------------------------------------------ files other tools read


def test_quality_sweep_files_are_strict_json_a_csv_with_header_and_a_png(tmp_path) -> None:
    """Few actions with few errors: a test split of one class, whose ROC AUC has no value."""
    args = [
        "eeg", "quality-sweep", "--out", str(tmp_path), "--quality", "0.5", "--seeds", "1",
        "--actions", "60", "--error-rate", "0.05", "--max-passes", "1", "--decoders", "lda",
    ]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    sweep = _strict_json(tmp_path / "quality_sweep.json")
    assert sweep["runs"][0]["roc_auc"] is None  # NaN written as null
    assert _strict_json(tmp_path / "quality_sweep.partial.json")[0]["roc_auc"] is None
    assert _csv_rows(tmp_path / "quality_sweep.csv")
    assert (tmp_path / "quality_sweep.png").read_bytes().startswith(PNG_SIGNATURE)


class _Subjects:
    """A virtual-subject factory that only says its settings (what a folder records)."""

    def __init__(self, *decoders: str) -> None:
        self.decoders = decoders or ("eegnet", "lda", "xdawn_rg")

    def __call__(self, seed: int, decoder_accuracy: float) -> Any:
        raise AssertionError("no run trains here")

    def describe(self) -> dict[str, Any]:
        return {"decoders": list(self.decoders), "max_passes": 3}

    def describe_defaults(self) -> dict[str, Any]:
        return _Subjects().describe()


def test_a_reproduction_folder_holds_one_decoder_set(tmp_path, monkeypatch) -> None:
    """Runs of another --decoders would be summarised in the same groups (and a run would
    resume with a pi_HF learned under other decoders): refused naming the setting."""

    def records(function, specs, *, workers, on_result, on_failure) -> None:
        for spec in specs:
            feedback = {"feedback": spec.feedback, "label_channel": spec.label_channel}
            on_result(
                replace(_record(spec), **feedback) if spec.method == "hf_sparse" else _record(spec)
            )

    monkeypatch.setattr(pool, "run_isolated", records)

    def subject_run(seed: int) -> RunSpec:
        return RunSpec("sssg", "hf_sparse", seed, feedback="virtual_subject", decoder_accuracy=0.7)

    study = tmp_path / "study"
    pool.reproduce(study, [subject_run(0)], feedback_factory=_Subjects("lda"), lockstep=False)
    with pytest.raises(
        ValueError, match=r"decoders \['lda'\], not \['eegnet', 'lda', 'xdawn_rg'\]"
    ):
        pool.reproduce(study, [subject_run(1)], feedback_factory=_Subjects(), lockstep=False)
    pool.reproduce(study, [subject_run(1)], feedback_factory=_Subjects("lda"), lockstep=False)
    # runs of the oracle's feedback need no factory and keep the folder's record
    pool.reproduce(study, [RunSpec("sssg", "rl_sparse", 0)], lockstep=False)
    config = _strict_json(study / "results.json")["config"]
    assert config["feedback_source"] == {"decoders": ["lda"], "max_passes": 3}
    # a folder written before the record: its virtual subjects had the default decoders
    document = _strict_json(study / "results.json")
    del document["config"]["feedback_source"]
    (study / "results.json").write_text(json.dumps(document))
    with pytest.raises(
        ValueError, match=r"decoders \['eegnet', 'lda', 'xdawn_rg'\], not \['lda'\]"
    ):
        pool.reproduce(study, [subject_run(2)], feedback_factory=_Subjects("lda"), lockstep=False)
    pool.reproduce(study, [subject_run(2)], feedback_factory=_Subjects(), lockstep=False)
    assert len(_strict_json(study / "results.json")["runs"]) == 4
