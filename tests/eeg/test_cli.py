"""``bgrl eeg calibrate`` on a tiny SYNTHETIC BDF file."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.eeg.virtual_subject import simulate_recording

runner = CliRunner()


@pytest.mark.slow
def test_cli_calibrate_tiny_bdf_misnamed_edf_without_library_noise(tmp_path) -> None:
    """The real command in its own process: a BDF named .edf is read as BDF and said so,
    and no library notice (torchvision, TorchScript deprecation) reaches the terminal."""
    from services.eeg.io import write_bdf

    labels = np.random.default_rng(0).random(60) >= 0.3
    path = write_bdf(simulate_recording(labels, quality=1.0, seed=2), tmp_path / "tiny.bdf")
    misnamed = path.rename(tmp_path / "tiny.edf")
    out = tmp_path / "model"
    command = [sys.executable, "-m", "services.cli.main", "eeg", "calibrate", str(misnamed)]
    done = subprocess.run(
        [*command, "--out", str(out), "--seed", "1", "--max-passes", "3"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert "SYNTHETIC" in done.stdout
    assert "tiny.edf: the file's header says BDF, not EDF; it is read as BDF" in done.stderr
    for noise in ("torchvision", "Warning", "deprecated", "Traceback"):
        assert noise not in done.stderr, done.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["n_epochs"] == 60 and metrics["n_params"] == 786
    assert metrics["passes_run"] == 3 and metrics["training_config"]["max_passes"] == 3
    assert {"test_accuracy", "balanced_accuracy", "roc_auc"} <= metrics.keys()
    assert (out / "classifier.json").is_file() and (out / "report.html").is_file()
    assert (out / "model.onnx").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "tiny.edf"]


def test_cli_calibrate_rejects_bad_file(tmp_path) -> None:
    bad = tmp_path / "bad.bdf"
    bad.write_bytes(b"not a bdf file")
    out = tmp_path / "model"
    result = runner.invoke(app, ["eeg", "calibrate", str(bad), "--out", str(out)])
    assert result.exit_code != 0
    assert "bad.bdf: not a readable BDF, EDF, FIF, BrainVision or XDF file" in result.output
    assert str(tmp_path) not in result.output
    assert not (out / "metrics.json").exists()
