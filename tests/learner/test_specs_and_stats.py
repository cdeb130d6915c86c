"""RunSpec / RunRecord, the results files of earlier sessions, summaries and claim checks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services.learner.outputs import load_results, write_outputs
from services.learner.runs import RunRecord, episode_stats, steps_to_reach
from services.learner.specs import RunSpec, build_specs, settings_conflict
from services.learner.stats import paper_claims, summarize

RESULTS = Path(__file__).parents[2] / "docs" / "results"


def test_run_spec_validates_and_round_trips() -> None:
    with pytest.raises(ValueError, match="accuracy is required"):
        RunSpec("sssg", "hf_sparse", 0)
    with pytest.raises(ValueError, match="unknown task"):
        RunSpec("maze", "rl_sparse", 0)
    with pytest.raises(ValueError, match="hf_treatment applies to hf_sparse only"):
        RunSpec("sssg", "rl_sparse", 0, hf_treatment="truncated_is")
    with pytest.raises(ValueError, match="cannot set \\['seed'\\]"):
        RunSpec("sssg", "rl_sparse", 0, ppo_overrides={"seed": 3})
    with pytest.raises(ValueError, match=r"ppo_overrides: .*no_such"):
        RunSpec("sssg", "rl_sparse", 0, ppo_overrides={"no_such": 3})
    spec = RunSpec("vssg", "hf_sparse", 3, 0.7, ppo_overrides={"n_epochs": 2})
    assert spec.hf_treatment == "authors"
    assert spec.to_dict() == {
        "task": "vssg", "method": "hf_sparse", "seed": 3, "accuracy": 0.7,
        "hf_treatment": "authors", "n_labels": 1000, "map_path": None,
        "ppo_overrides": {"n_epochs": 2}, "hf_method": "paper", "feedback": "oracle",
        "label_channel": "hard", "decoder_accuracy": None,
    }  # fmt: skip
    assert RunSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    assert spec.label == "vssg hf_sparse C=0.7 [authors] seed=3"
    assert RunSpec("sssg", "rl_sparse", 0).hf_method is None
    with pytest.raises(ValueError, match="unknown stage-2 method 'nope'"):
        RunSpec("sssg", "hf_sparse", 0, 0.6, hf_method="nope")
    with pytest.raises(ValueError, match="hf_method applies to hf_sparse only"):
        RunSpec("sssg", "rl_sparse", 0, hf_method="categorical")
    platform = RunSpec("sssg", "hf_sparse", 0, 0.6, hf_method="categorical_thompson")
    assert platform.label.endswith("[authors] categorical_thompson seed=0")
    assert platform.key != RunSpec("sssg", "hf_sparse", 0, 0.6).key
    config = spec.ppo_config()
    assert (config.seed, config.n_epochs, config.env_kwargs) == (3, 2, {"reward_mode": "sparse"})
    assert len(config.eval_seeds) == 5
    specs = build_specs(seeds=2, tasks=["sssg"], treatments=["authors", "truncated_is"])
    assert len(specs) == 2 * (2 + 2 * 3)
    assert not settings_conflict(specs)
    more_labels = build_specs(seeds=1, tasks=["sssg"], methods=["rl_sparse", "hf_sparse"],
                              accuracies=[0.6], n_labels=4000)  # fmt: skip
    assert [(s.method, s.n_labels) for s in more_labels] == [
        ("rl_sparse", 1000), ("hf_sparse", 4000),
    ]  # fmt: skip
    assert settings_conflict([*specs, *more_labels])  # one label count per output folder
    assert settings_conflict([*specs, RunSpec("sssg", "rl_sparse", 5, map_path="x.json")])
    # one stage-2 method per folder: the summary and CSV cannot tell two apart
    kernel = RunSpec("sssg", "hf_sparse", 0, 0.6, hf_method="categorical_kernel")
    assert settings_conflict([*specs, kernel])
    assert not settings_conflict([kernel, RunSpec("sssg", "rl_sparse", 0)])
    shaped = RunSpec("vssg", "rl_shaped", 1, ppo_overrides={"gamma": 0.95}).ppo_config()
    assert shaped.env_kwargs == {"reward_mode": "shaped", "shaping_gamma": 0.95}
    dense = RunSpec("vssg", "rl_rich", 1, ppo_overrides={"gamma": 0.9}).ppo_config()
    assert dense.env_kwargs == {"reward_mode": "dense", "shaping_gamma": 0.9}
    with pytest.raises(ValueError, match="accuracy is required"):
        RunSpec("sssg", "rl_shaped", 0, accuracy=0.7)


@pytest.mark.parametrize("study", ["reproduce", "truncated_is_sampling", "pocket"])
def test_results_of_earlier_sessions_still_load(study) -> None:
    results = load_results(RESULTS / study / "results.json")
    assert results.failed == []
    assert all(r.run_spec.key == (r.task, r.method, r.accuracy, r.seed, r.hf_treatment)
               for r in results.runs)  # fmt: skip
    raw = json.loads((RESULTS / study / "results.json").read_text())["runs"]
    added = {"best_step": None, "best_spl": None, "environment": None}  # newer than these records
    for run in raw:  # the record format's feedback fields, from each run's spec
        hf = run["method"] == "hf_sparse"
        feedback = {"n_labels": run["spec"]["n_labels"] if hf else 0,
                    "feedback": "oracle" if hf else None,
                    "label_channel": "hard" if hf else None, "decoder_accuracy": None,
                    "subject_quality": None}  # fmt: skip
        run.update({**added, **feedback})
    assert [r.to_dict() for r in results.runs] == raw


def test_steps_to_reach_and_episode_stats() -> None:
    assert steps_to_reach([[0, 0.1], [100, 0.7], [200, 0.9]]) == 100
    assert steps_to_reach([[0, 0.1], [100, 0.69]]) is None
    episodes = [(100, 100, False, True, True), (1500, 40, True, False, False), (2100, 9, 0, 1, 0)]
    rows = episode_stats(episodes, window=1000, total_steps=3000)
    assert [r["episodes"] for r in rows] == [1, 1, 1]
    assert rows[0] == {
        "steps": 1000, "episodes": 1, "hf_episodes": 1, "mean_length": 100.0,
        "success_rate": 0.0, "collision_rate": 1.0,
    }  # fmt: skip
    assert rows[1]["success_rate"] == 1.0


def _run(method: str, seed: int, curve: list[float], accuracy=None, hf_spl=None) -> RunRecord:
    steps = [[2000 * k, spl] for k, spl in enumerate(curve)]
    return RunRecord(
        task="vssg", method=method, accuracy=accuracy, seed=seed,
        hf_treatment="authors" if method == "hf_sparse" else None, curve=steps,
        final_spl=curve[-1], hf_policy_spl=hf_spl, wall_seconds=1.0,
        steps_to_0_7=steps_to_reach(steps),
    )  # fmt: skip


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
    flat = [
        RunRecord.from_dict({**r.to_dict(), "hf_policy_spl": 0.1}) if r.method == "hf_sparse" else r
        for r in runs
    ]
    flat_verdicts = {c["claim"]: c["holds"] for c in paper_claims(summarize(flat))}
    assert flat_verdicts["HF policy SPL increases with C [authors]"] is False


def _subject_run(seed: int, curve: list[float], decoder_accuracy: float) -> RunRecord:
    spec = RunSpec(
        "vssg", "hf_sparse", seed, hf_treatment="truncated_is", feedback="virtual_subject",
        label_channel="soft", decoder_accuracy=0.6,
    )  # fmt: skip
    run = _run("hf_sparse", seed, curve, None, 0.5)
    return RunRecord.from_dict(
        {
            **run.to_dict(),
            "hf_treatment": "truncated_is",
            "spec": spec.to_dict(),
            "feedback": "virtual_subject",
            "label_channel": "soft",
            "decoder_accuracy": decoder_accuracy,
            "subject_quality": 0.1,
        }
    )


def test_a_virtual_subject_study_is_summarised_with_its_decoders_misses(tmp_path) -> None:
    """``bgrl reproduce --feedback virtual_subject`` crashed formatting C = None; a subject
    whose decoder missed its target by more than 0.02 is kept and named."""
    runs = [
        _run("rl_sparse", 0, [0, 0, 0, 0]),
        _run("rl_sparse", 1, [0, 0, 0.8, 0.8]),
        _subject_run(0, [0, 0.8, 0.9, 0.9], 0.61),
        _subject_run(1, [0, 0, 0.9, 0.9], 0.55),
    ]
    write_outputs(tmp_path, runs)
    (row,) = [r for r in summarize(runs) if r["method"] == "hf_sparse"]
    assert row["group"] == "hf_sparse subject@0.6 soft [truncated_is]" and row["n_seeds"] == 2
    assert row["decoder_accuracy_target"] == 0.6
    assert row["decoder_accuracy_mean"] == pytest.approx(0.58)
    assert row["decoder_off_target"] == [{"seed": 1, "target": 0.6, "decoder_accuracy": 0.55}]
    summary = (tmp_path / "summary.md").read_text()
    assert "| VSSG | hf_sparse subject@0.6 soft [truncated_is] | 2 |" in summary
    assert "outside the target's tolerance (kept): seed 1 0.550" in summary
    claims = {c["claim"] for c in paper_claims(summarize(runs))}
    assert not any("increases with C" in claim for claim in claims)  # C is the oracle's
