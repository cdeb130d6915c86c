"""`bgrl hf-sweep --labels/--method` and `bgrl reproduce --preset` (stage 2's interface)."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.learner import pool
from services.learner.hf_methods import PAPER_METHOD, RECOMMENDED_METHOD
from services.learner.specs import apply_preset


def test_presets() -> None:
    assert apply_preset("paper", ["authors"], {}) == (["authors"], {}, PAPER_METHOD)
    assert apply_preset("platform", ["authors"], {"n_epochs": 10}) == (
        ["truncated_is"], {"n_epochs": 10, "hf_guide_sampling": True, "sil_coef": 1.0},
        RECOMMENDED_METHOD,
    )  # fmt: skip
    # what is given explicitly is kept
    given = {"hf_guide_sampling": False, "sil_coef": 0.0}
    assert apply_preset("platform", ["authors", "truncated_is"], given) == (
        ["authors", "truncated_is"], given, RECOMMENDED_METHOD,
    )  # fmt: skip
    with pytest.raises(ValueError, match="preset: unknown preset 'lab'"):
        apply_preset("lab", ["authors"], {})


def _in_process(function, specs, *, workers, on_result, on_failure) -> None:
    """``pool.run_isolated`` without the spawned workers (they cost seconds each to start)."""
    for spec in specs:
        on_result(function(spec))


def test_hf_sweep_over_labels_and_methods_writes_rows_table_plot_and_resumes(
    tmp_path, monkeypatch
) -> None:
    monkeypatch.setattr(pool, "run_isolated", _in_process)
    args = [
        "hf-sweep", "--out", str(tmp_path), "--seeds", "1", "--tasks", "sssg",
        "--accuracies", "0.7", "--labels", "20,30", "--method", "paper,categorical",
    ]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    rows = json.loads((tmp_path / "hf_policies.json").read_text())["runs"]
    assert sorted((r["method"], r["n_labels"]) for r in rows) == [
        ("categorical", 20), ("categorical", 30), ("paper", 20), ("paper", 30),
    ]  # fmt: skip
    assert all(r["config"]["method"] == r["method"] for r in rows)  # recorded in the model's config
    summary = (tmp_path / "summary.md").read_text()
    assert "| categorical | SSSG | 0.7 | 30 | 1 |" in summary
    assert (tmp_path / "spl_vs_labels.png").stat().st_size > 0
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0
    assert len(json.loads((tmp_path / "hf_policies.json").read_text())["runs"]) == 4


@pytest.mark.parametrize(
    ("option", "message"),
    [("--method=nope", "unknown stage-2 method 'nope'"), ("--labels=0", "--labels must be")],
)
def test_hf_sweep_refuses_bad_input_naming_the_option(tmp_path, option, message) -> None:
    result = CliRunner().invoke(app, ["hf-sweep", "--out", str(tmp_path / "x"), option])
    assert result.exit_code == 2 and message in result.output
    assert not (tmp_path / "x").exists()


def test_reproduce_hf_method_replaces_the_presets_stage2_method(tmp_path, monkeypatch) -> None:
    captured = []

    def fake_reproduce(out, specs, **kwargs):
        captured.append((list(specs), kwargs["config_note"]["cli"]))
        (out / "summary.md").parent.mkdir(parents=True, exist_ok=True)
        (out / "summary.md").write_text("table")
        return type("Results", (), {"failed": []})()

    monkeypatch.setattr(pool, "reproduce", fake_reproduce)
    base = ["reproduce", "--out", str(tmp_path), "--seeds", "1", "--tasks", "sssg"]
    base += ["--methods", "rl_sparse,hf_sparse", "--accuracies", "0.6"]
    for extra, expected in [
        ([], RECOMMENDED_METHOD),  # the preset's
        (["--hf-method", "categorical_kernel"], "categorical_kernel"),
    ]:
        result = CliRunner().invoke(app, [*base, "--preset", "platform", *extra])
        assert result.exit_code == 0, result.output
        specs, cli = captured.pop()
        assert cli["hf_method"] == expected and cli["preset"] == "platform"
        assert [s.hf_method for s in specs if s.method == "hf_sparse"] == [expected]
        assert [s.hf_method for s in specs if s.method == "rl_sparse"] == [None]
        assert [s.n_labels for s in specs] == [1000, 1000] and cli["labels"] == 1000
    result = CliRunner().invoke(app, [*base, "--labels", "4000"])
    assert result.exit_code == 0, result.output
    specs, cli = captured.pop()
    assert {s.method: s.n_labels for s in specs} == {"rl_sparse": 1000, "hf_sparse": 4000}
    assert cli["labels"] == 4000
    result = CliRunner().invoke(app, [*base, "--labels", "0"])
    assert result.exit_code == 2 and "--labels" in result.output
    result = CliRunner().invoke(app, [*base, "--hf-method", "nope"])
    assert result.exit_code == 2 and "unknown stage-2 method 'nope'" in result.output
    assert not captured


@pytest.mark.parametrize(
    ("options", "refusal"),
    [
        (["--label-channel", "soft"], "soft label channel"),
        (["--feedback", "virtual_subject"], "give the target accuracies"),
        (["--feedback", "virtual_subject", "--decoder-accuracy", "0.45"], "not in (0.5, 1)"),
        (["--decoder-accuracy", "0.6"], "applies to"),
        (["--feedback", "lab"], "expected one of"),
        (["--feedback", "virtual_subject", "--decoder-accuracy", "0.6", "--decoders", "x"], "x"),
    ],
)
def test_feedback_options_are_refused_before_anything_runs(tmp_path, options, refusal) -> None:
    for command in ("reproduce", "hf-sweep", "hf-nstar"):
        out = tmp_path / command
        result = CliRunner().invoke(app, [command, "--out", str(out), *options])
        assert result.exit_code == 2, result.output
        assert refusal in " ".join(result.output.split()), result.output
        assert not out.exists()


def _subject_rows(function, specs, *, workers, on_result, on_failure) -> None:
    """``pool.run_isolated`` making each single run's row without learning (no subject is
    simulated, no decoder trained): what the folder records is under test, not the rows."""
    for spec in specs:
        on_result(
            {**spec.to_dict(), "decoder_accuracy_target": spec.decoder_accuracy,
             "greedy_spl": 0.0, "sampled_success_rate": 0.0}
        )  # fmt: skip


def test_an_hf_sweep_folder_holds_one_decoder_set(tmp_path, monkeypatch) -> None:
    """Rows of another --decoders would be grouped with these (and their runs skipped as
    done): refused naming the setting and the folder, the file left as it is."""
    monkeypatch.setattr(pool, "run_isolated", _subject_rows)
    out = tmp_path / "sweep"
    base = ["hf-sweep", "--out", str(out), "--tasks", "sssg", "--labels", "20", "--single-run"]
    subject = [*base, "--feedback", "virtual_subject", "--decoder-accuracy", "0.6"]

    def document() -> dict:
        return json.loads((out / "hf_policies.json").read_text())

    result = CliRunner().invoke(app, [*subject, "--seeds", "1", "--decoders", "lda"])
    assert result.exit_code == 0, result.output
    recorded = document()["config"]["feedback_source"]
    assert recorded["decoders"] == ["lda"] and "max_passes" in recorded
    before = (out / "hf_policies.json").read_text()
    refused = CliRunner().invoke(app, [*subject, "--seeds", "2"])  # the default decoders
    assert refused.exit_code == 2, refused.output
    message = _flat(refused.output)
    assert _flat("decoders ['lda'], not ['eegnet', 'lda', 'xdawn_rg']") in message
    assert _flat(f"{out} holds virtual-subject runs") in message
    assert (out / "hf_policies.json").read_text() == before
    # runs of the oracle's feedback need no decoders and keep the folder's record
    result = CliRunner().invoke(app, [*base, "--seeds", "1", "--accuracies", "0.7"])
    assert result.exit_code == 0, result.output
    assert document()["config"]["feedback_source"] == recorded and len(document()["runs"]) == 2
    # a file written before the record: its virtual subjects had the default decoders
    old = document()
    del old["config"]
    (out / "hf_policies.json").write_text(json.dumps(old))
    assert pool.load_sweep(out / "hf_policies.json").feedback_source is None
    refused = CliRunner().invoke(app, [*subject, "--seeds", "2", "--decoders", "lda"])
    assert refused.exit_code == 2
    assert _flat("decoders ['eegnet', 'lda', 'xdawn_rg'], not ['lda']") in _flat(refused.output)
    result = CliRunner().invoke(app, [*subject, "--seeds", "2"])
    assert result.exit_code == 0, result.output
    assert document()["config"]["feedback_source"]["decoders"] == ["eegnet", "lda", "xdawn_rg"]
    assert len(document()["runs"]) == 3


def _flat(text: str) -> str:
    """``text`` without spaces and box borders (the CLI's error box wraps its lines)."""
    return "".join(text.replace("│", "").split())
