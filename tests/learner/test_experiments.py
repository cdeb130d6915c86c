"""The reproduction pipeline on the real env, at a tiny budget: records, files, schema."""

from __future__ import annotations

import json

import pytest

from services.learner.experiments import (
    build_specs,
    compare_studies,
    episode_stats,
    hf_policy_run,
    make_spec,
    paper_claims,
    reproduce,
    run_one,
    steps_to_reach,
    summarize,
)

TINY = {"total_steps": 256, "eval_every": 128, "n_epochs": 2}


def test_make_spec_validates() -> None:
    with pytest.raises(ValueError, match="accuracy is required"):
        make_spec("sssg", "hf_sparse", 0)
    with pytest.raises(ValueError, match="unknown task"):
        make_spec("maze", "rl_sparse", 0)
    specs = build_specs(seeds=2, tasks=["sssg"], treatments=["authors", "truncated_is"])
    assert len(specs) == 2 * (2 + 2 * 3)


def test_steps_to_reach() -> None:
    assert steps_to_reach([[0, 0.1], [100, 0.7], [200, 0.9]]) == 100
    assert steps_to_reach([[0, 0.1], [100, 0.69]]) is None


def test_run_one_hf_sparse_on_the_real_env() -> None:
    spec = make_spec(
        "vssg", "hf_sparse", 3, accuracy=0.7, hf_treatment="truncated_is", n_labels=60,
        ppo_overrides=TINY,
    )  # fmt: skip
    record = run_one(spec)
    assert record["method"] == "hf_sparse" and record["hf_treatment"] == "truncated_is"
    assert [step for step, _ in record["curve"]] == [0, 128, 256]
    assert 0.0 <= record["hf_policy_spl"] <= 1.0
    assert record["hf"]["n_labels"] == 60 and 0.5 < record["hf"]["label_accuracy"] < 0.9


def test_reproduce_writes_results_json_with_the_schema(tmp_path) -> None:
    specs = [
        make_spec("sssg", "rl_sparse", 0, ppo_overrides=TINY),
        make_spec("sssg", "rl_rich", 0, ppo_overrides=TINY),
        make_spec("sssg", "hf_sparse", 0, accuracy=0.6, n_labels=40, ppo_overrides=TINY),
    ]
    document = reproduce(tmp_path, specs, workers=1)
    on_disk = json.loads((tmp_path / "results.json").read_text())
    assert on_disk == json.loads(json.dumps(document))
    assert on_disk["config"]["ppo"]["total_steps"] == 40_000  # defaults recorded
    runs = on_disk["runs"]
    assert len(runs) == 3
    required = {
        "task": str, "method": str, "seed": int, "curve": list, "final_spl": float,
        "wall_seconds": float,
    }  # fmt: skip
    for run in runs:
        for key, kind in required.items():
            assert isinstance(run[key], kind), key
        assert all(len(point) == 2 for point in run["curve"])
        assert run["final_spl"] == run["curve"][-1][1]
        if run["method"] == "hf_sparse":
            assert run["accuracy"] == 0.6 and isinstance(run["hf_policy_spl"], float)
        else:
            assert run["accuracy"] is None and run["hf_policy_spl"] is None
    for name in ("results.csv", "summary.md", "summary.json", "fig3_sssg.png"):
        assert (tmp_path / name).stat().st_size > 0
    summary_doc = json.loads((tmp_path / "summary.json").read_text())
    assert {c["claim"] for c in summary_doc["claims"]} >= {"RL-sparse final SPL <= 0.3"}
    assert {row["group"] for row in summarize(runs)} == {
        "rl_sparse", "rl_rich", "hf_sparse C=0.6",
    }  # fmt: skip
    # A second call finds every run done and only rewrites the outputs.
    skipped: list[int] = []
    again = reproduce(tmp_path, specs, workers=1, on_resume=skipped.append)
    assert [r["wall_seconds"] for r in again["runs"]] == [r["wall_seconds"] for r in runs]
    assert skipped == [3]
    other = make_spec("sssg", "rl_sparse", 1, ppo_overrides={**TINY, "reward_scale": 1.0})
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


def test_hf_policy_run_measures_stage_two_alone() -> None:
    row = hf_policy_run("sssg", 0.7, 0, n_labels=60)
    assert row["n_labels"] == 60 and 0.0 <= row["greedy_spl"] <= 1.0
    assert 0.0 <= row["sampled_success_rate"] <= 1.0
    assert row["validation_accuracy_true"] is not None


def test_episode_stats_windows() -> None:
    episodes = [(100, 100, False, True, True), (1500, 40, True, False, False), (2100, 9, 0, 1, 0)]
    rows = episode_stats(episodes, window=1000, total_steps=3000)
    assert [r["episodes"] for r in rows] == [1, 1, 1]
    assert rows[0] == {
        "steps": 1000, "episodes": 1, "hf_episodes": 1, "mean_length": 100.0,
        "success_rate": 0.0, "collision_rate": 1.0,
    }  # fmt: skip
    assert rows[1]["success_rate"] == 1.0


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


def _run(method: str, seed: int, curve: list[float], accuracy=None, hf_spl=None) -> dict:
    steps = [[2000 * k, spl] for k, spl in enumerate(curve)]
    return {
        "task": "vssg", "method": method, "accuracy": accuracy, "seed": seed,
        "hf_treatment": "authors" if method == "hf_sparse" else None, "curve": steps,
        "final_spl": curve[-1], "hf_policy_spl": hf_spl,
        "steps_to_0_7": next((s for s, v in steps if v >= 0.7), None),
    }  # fmt: skip


def test_paper_claims_verdicts() -> None:
    runs = [
        _run("rl_sparse", 0, [0, 0, 0, 0.8]),  # mean curve 0.4 at the end
        _run("rl_sparse", 1, [0, 0, 0, 0.0]),
        _run("rl_rich", 0, [0, 0.9, 0.9, 0.9]),
        _run("rl_rich", 1, [0, 0.5, 0.8, 0.7]),
        _run("hf_sparse", 0, [0, 0.8, 0.9, 0.9], 0.7, 0.4),
        _run("hf_sparse", 1, [0, 0.6, 0.9, 0.8], 0.7, 0.2),
        _run("hf_sparse", 0, [0, 0, 0.2, 0.3], 0.6, 0.1),
        _run("hf_sparse", 1, [0, 0, 0.2, 0.3], 0.6, 0.1),
        _run("hf_sparse", 0, [0, 0, 0, 0], 0.55, 0.0),
    ]
    verdicts = {c["claim"]: c["holds"] for c in paper_claims(summarize(runs))}
    assert verdicts == {
        "RL-sparse final SPL <= 0.3": False,  # mean 0.4
        "RL-rich final SPL >= 0.8": True,  # mean 0.8
        "HF+sparse C=0.55: reported as measured": None,
        "HF+sparse C=0.6 final SPL >= 0.8": False,
        "HF+sparse C=0.6 reaches 0.7 sooner than RL-sparse ever does": False,
        "HF+sparse C=0.7 final SPL >= 0.8": True,  # mean 0.85
        "HF+sparse C=0.7 reaches 0.7 sooner than RL-sparse ever does": True,  # 2000 vs never
        "HF policy SPL increases with C [authors]": True,  # 0.0, 0.1, 0.3
        # 2 runs against 2: a one-sided Mann-Whitney p is at least 1/6
        "HF+sparse C=0.6 learns faster than RL-sparse (supplementary)": False,
        "HF+sparse C=0.7 learns faster than RL-sparse (supplementary)": False,
    }
    many = runs + [
        _run(method, seed, curve, accuracy, 0.3)
        for seed in range(2, 8)
        for method, curve, accuracy in [
            ("rl_sparse", [0, 0, 0, 0], None),
            ("hf_sparse", [0, 0.8, 0.9, 0.9], 0.7),
        ]
    ]
    supplementary = {c["claim"]: c for c in paper_claims(summarize(many))}
    faster = supplementary["HF+sparse C=0.7 learns faster than RL-sparse (supplementary)"]
    assert faster["holds"] is True and faster["n_seeds"] == 8
    flat = [r | {"hf_policy_spl": 0.1} if r["method"] == "hf_sparse" else r for r in runs]
    flat_verdicts = {c["claim"]: c["holds"] for c in paper_claims(summarize(flat))}
    assert flat_verdicts["HF policy SPL increases with C [authors]"] is False


def test_cli_refuses_bad_input_with_a_clear_message(tmp_path) -> None:
    from typer.testing import CliRunner

    from services.cli.main import app

    runner = CliRunner()
    result = runner.invoke(app, ["reproduce", "--out", str(tmp_path / "r"), "--ppo", "n_epochs"])
    assert result.exit_code == 2 and "KEY=VALUE" in result.output
    assert not (tmp_path / "r").exists()  # nothing written
    result = runner.invoke(app, ["compare", str(tmp_path), "--out", str(tmp_path / "c")])
    assert result.exit_code == 2 and "not a `bgrl reproduce` folder" in result.output
    assert not (tmp_path / "c").exists()
