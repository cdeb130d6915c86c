"""``bgrl eeg calibrate`` on a tiny SYNTHETIC BDF file."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from services.cli.main import app
from services.eeg.virtual_subject import simulate_recording

runner = CliRunner()


def test_cli_calibrate_tiny_bdf(tmp_path) -> None:
    from services.eeg.io import write_bdf

    labels = np.random.default_rng(0).random(60) >= 0.3
    path = write_bdf(simulate_recording(labels, quality=1.0, seed=2), tmp_path / "tiny.bdf")
    out = tmp_path / "model"
    result = runner.invoke(
        app, ["eeg", "calibrate", str(path), "--out", str(out), "--seed", "1", "--max-passes", "3"]
    )
    assert result.exit_code == 0, result.output
    assert "SYNTHETIC" in result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_epochs"] == 60 and metrics["n_params"] == 786
    assert {"test_accuracy", "balanced_accuracy", "roc_auc"} <= metrics.keys()
    assert (out / "classifier.json").is_file() and (out / "report.html").is_file()


def test_cli_calibrate_rejects_bad_file(tmp_path) -> None:
    bad = tmp_path / "bad.bdf"
    bad.write_bytes(b"not a bdf file")
    out = tmp_path / "model"
    result = runner.invoke(app, ["eeg", "calibrate", str(bad), "--out", str(out)])
    assert result.exit_code != 0
    assert not (out / "metrics.json").exists()
