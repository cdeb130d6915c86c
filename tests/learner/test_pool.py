"""The reproduction pipeline on the real env at a tiny budget: records, files, resume,
failure isolation, the CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from services.cli.main import app
from services.learner import pool
from services.learner.outputs import compare_studies, load_results
from services.learner.pool import reproduce, run_isolated
from services.learner.runs import HFPolicySpec, RunFailure, RunRecord, hf_policy_run, run_one
from services.learner.specs import RunSpec
from services.learner.stats import summarize

TINY = {"total_steps": 256, "eval_every": 128, "n_epochs": 2}
DEFAULT_MAP = Path(__file__).parents[2] / "services" / "sim" / "maps" / "default.json"


def test_run_one_hf_sparse_on_the_real_env() -> None:
    spec = RunSpec("vssg", "hf_sparse", 3, 0.7, "truncated_is", n_labels=60, ppo_overrides=TINY)
    record = run_one(spec)
    assert (record.method, record.hf_treatment, record.run_spec) == (
        "hf_sparse", "truncated_is", spec,
    )  # fmt: skip
    assert record.curve == [[0, 0.0], [128, 0.0], [256, 0.0]] and record.hf_policy_spl == 0.0
    # the label noise comes from the seed's own stream: 41 of the 60 labels are right
    assert record.hf["n_labels"] == 60 and record.hf["label_accuracy"] == pytest.approx(41 / 60)
    assert RunRecord.from_dict(json.loads(json.dumps(record.to_dict()))) == record
    # what a bit-for-bit repeat needs: the versions the numbers depend on
    assert record.environment is not None
    assert record.environment["torch"] == torch.__version__
    assert {"python", "numpy", "gymnasium", "pybullet", "cpu_capability"} <= set(record.environment)


def test_hf_policy_run_measures_stage_two_alone() -> None:
    row = hf_policy_run(HFPolicySpec("sssg", 0.7, 0, n_labels=60))
    assert (row["n_labels"], row["greedy_spl"], row["sampled_success_rate"]) == (60, 0.0, 0.0)
    assert row["label_accuracy"] == pytest.approx(43 / 60)


def test_reproduce_writes_results_json_and_resumes(tmp_path) -> None:
    specs = [
        RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY),
        RunSpec("sssg", "rl_rich", 0, ppo_overrides=TINY),
        RunSpec("sssg", "hf_sparse", 0, 0.6, n_labels=40, ppo_overrides=TINY),
    ]
    results = reproduce(tmp_path, specs, workers=1)
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(results.to_dict()))
    assert on_disk["config"]["ppo"]["total_steps"] == 40_000  # defaults recorded
    assert on_disk["failed"] == []
    assert sorted(r.run_spec.key for r in results.runs) == sorted(s.key for s in specs)
    for run in results.runs:
        assert [step for step, _ in run.curve] == [0, 128, 256]
        assert run.final_spl == run.curve[-1][1]
        assert (run.hf_policy_spl is None) == (run.method != "hf_sparse")
    for name in ("results.csv", "summary.md", "summary.json", "fig3_sssg.png"):
        assert (tmp_path / name).stat().st_size > 0
    summary_doc = json.loads((tmp_path / "summary.json").read_text())
    assert {c["claim"] for c in summary_doc["claims"]} >= {"RL-sparse final SPL <= 0.3"}
    assert {row["group"] for row in summarize(results.runs)} == {
        "rl_sparse", "rl_rich", "hf_sparse C=0.6",
    }  # fmt: skip
    # A second call finds every run done and only rewrites the outputs.
    skipped: list[int] = []
    again = reproduce(tmp_path, specs, workers=1, on_resume=skipped.append)
    assert again.runs == results.runs and skipped == [3]
    other = RunSpec("sssg", "rl_sparse", 1, ppo_overrides={**TINY, "reward_scale": 1.0})
    with pytest.raises(ValueError, match="other settings"):
        reproduce(tmp_path, [other], workers=1)
    # Studies side by side: one row per study and group, the overrides named.
    rows = compare_studies([tmp_path], tmp_path / "compare")
    assert {(r["study"], r["group"]) for r in rows} == {
        (tmp_path.name, g) for g in ("rl_sparse", "rl_rich", "hf_sparse C=0.6")
    }
    assert "n_epochs=2" in (tmp_path / "compare" / "compare.md").read_text()
    assert (tmp_path / "compare" / "compare_sssg.png").stat().st_size > 0
    with pytest.raises(ValueError, match="not a `bgrl reproduce` folder"):
        compare_studies([tmp_path / "compare"], tmp_path / "compare2")


def _never(*args, **kwargs) -> None:
    raise AssertionError("a sweep naming a run twice must be refused before anything runs")


def test_a_sweep_naming_one_run_twice_is_refused_before_anything_runs(
    tmp_path, monkeypatch
) -> None:
    """From Python, as the CLI's repeated entries: the run would be trained twice and count
    as two seeds (and in lockstep share one checkpoint file)."""
    monkeypatch.setattr(pool, "run_isolated", _never)
    specs = [RunSpec("sssg", "rl_sparse", seed, ppo_overrides=TINY) for seed in (0, 1)]
    with pytest.raises(ValueError, match="sssg rl_sparse seed=1 given twice"):
        reproduce(tmp_path / "study", [*specs, specs[1]], workers=1)
    with pytest.raises(ValueError, match=r"sssg C=0\.7 seed=0 labels=20 paper given twice"):
        pool.hf_policy_sweep(
            tmp_path / "sweep", tasks=("sssg", "sssg"), accuracies=(0.7,), seeds=1, labels=(20,)
        )
    assert not (tmp_path / "study").exists() and not (tmp_path / "sweep").exists()


def test_a_failing_run_is_recorded_and_the_others_kept(tmp_path) -> None:
    bad_map = tmp_path / "bad.json"
    bad_map.write_text("not a map")
    good = RunSpec("sssg", "rl_sparse", 0, ppo_overrides=TINY)
    bad = RunSpec("sssg", "rl_sparse", 1, map_path=str(bad_map), ppo_overrides=TINY)
    records: list[RunRecord] = []
    failures: list[RunFailure] = []
    run_isolated(
        run_one, [bad, good], workers=1, on_result=records.append, on_failure=failures.append
    )
    assert [r.run_spec for r in records] == [good]
    [failure] = failures
    assert failure.spec == bad.to_dict() and failure.error_type == "MapError"
    assert f"map file {bad_map} is not valid JSON" in failure.message
    assert "load_map" in failure.traceback and str(failure).startswith("sssg rl_sparse seed=1: ")


def test_reproduce_keeps_failures_and_retries_them(tmp_path, monkeypatch) -> None:
    runner = CliRunner()
    study = tmp_path / "study"
    bad_map = tmp_path / "map.json"
    bad_map.write_text("{}")
    args = ["reproduce", "--out", str(study), "--seeds", "1", "--tasks", "sssg", "--methods",
            "rl_sparse", "--map", str(bad_map), "--ppo", "total_steps=256", "--ppo",
            "eval_every=128", "--ppo", "n_epochs=2", "--workers", "1"]  # fmt: skip
    # A map that fails in the worker, not before (validation skipped): the run is recorded.
    monkeypatch.setattr(pool, "validate_maps", lambda specs: None)
    result = runner.invoke(app, args)
    assert result.exit_code == 1
    assert "1 run(s) failed" in result.output and "sssg rl_sparse seed=0: MapError" in result.output
    failed = load_results(study / "results.json").failed
    assert [f.spec["seed"] for f in failed] == [0] and failed[0].error_type == "MapError"
    # The map repaired, the same command retries the failed run and nothing else fails.
    shutil.copy(DEFAULT_MAP, bad_map)
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    results = load_results(study / "results.json")
    assert results.failed == [] and [r.seed for r in results.runs] == [0]


def test_cli_refuses_bad_input_with_one_clear_line(tmp_path) -> None:
    runner = CliRunner()
    result = runner.invoke(app, ["reproduce", "--out", str(tmp_path / "r"), "--ppo", "n_epochs"])
    assert result.exit_code == 2 and "KEY=VALUE" in result.output
    result = runner.invoke(app, ["reproduce", "--out", str(tmp_path / "r"), "--map", "/etc/passwd"])
    assert result.exit_code == 2 and "map file /etc/passwd is not valid JSON" in result.output
    assert "Traceback" not in result.output
    assert not (tmp_path / "r").exists()  # nothing written
    result = runner.invoke(app, ["compare", str(tmp_path), "--out", str(tmp_path / "c")])
    assert result.exit_code == 2 and "not a `bgrl reproduce` folder" in result.output
    assert not (tmp_path / "c").exists()


def test_cli_ppo_overrides_are_typed_and_checked() -> None:
    from services.cli.learner import parse_ppo_overrides

    assert parse_ppo_overrides(["n_epochs=10", "reward_scale=1", "hf_guide_sampling=true"]) == {
        "n_epochs": 10,
        "reward_scale": 1.0,
        "hf_guide_sampling": True,
    }
    assert parse_ppo_overrides(["hidden_sizes=32,32"]) == {"hidden_sizes": (32, 32)}
    for bad, message in [
        (["n_epochs"], "KEY=VALUE"),
        (["n_epochs=ten"], "not a valid int"),
        (["no_such=1"], "unknown PPO setting"),
        (["seed=3"], "set per run"),
        (["hf_guide_sampling=maybe"], "not a valid bool"),
        (["minibatch_size=100"], "multiple of minibatch_size"),
    ]:
        with pytest.raises(ValueError, match=message):
            parse_ppo_overrides(bad)


def test_pool_processes_die_with_a_parent_killed_by_sigkill(tmp_path: Path) -> None:
    """A job worker running a reproduction is SIGKILLed (or restarted by ``bgrl up``): its
    run pool's processes end too, none keeps computing as an orphan of init."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script = (
        "import time; from services.learner.pool import run_isolated; "
        "run_isolated(time.sleep, [120, 120], workers=2, on_result=print, on_failure=print)"
    )
    parent = subprocess.Popen([sys.executable, "-c", script])

    def pool_children() -> list[int]:
        found = []
        for entry in Path("/proc").iterdir():
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                cmdline = (entry / "cmdline").read_bytes()
            except (OSError, IndexError):
                continue
            if int(stat[1]) == parent.pid and b"spawn_main" in cmdline and stat[0] != "Z":
                found.append(int(entry.name))
        return found

    def alive(pid: int) -> bool:
        try:
            return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
        except OSError:
            return False

    try:
        deadline = time.monotonic() + 60
        while len(children := pool_children()) < 2:
            assert time.monotonic() < deadline, "the pool did not start"
            time.sleep(0.1)
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 60  # a child still importing torch ends once it ran
        while [pid for pid in children if alive(pid)]:
            assert time.monotonic() < deadline, "a pool process outlived its parent"
            time.sleep(0.1)
    finally:
        if parent.poll() is None:
            parent.kill()
