"""``bgrl eeg calibrate`` on a tiny SYNTHETIC BDF file."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.eeg.virtual.subject import simulate_recording

runner = CliRunner()


@pytest.mark.slow
def test_cli_calibrate_tiny_bdf_misnamed_edf_without_library_noise(tmp_path) -> None:
    """The real command in its own process: a BDF named .edf is read as BDF and said so,
    and no library notice (torchvision, TorchScript deprecation) reaches the terminal."""
    from services.eeg.recordings.io import write_bdf

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
    assert metrics["n_epochs"] == 60 and metrics["decoders"]["eegnet"]["n_params"] == 786
    assert metrics["n_params"] == metrics["decoders"][metrics["decoder"]]["n_params"]
    assert f"{metrics['decoder']} (kept): validation accuracy" in done.stdout
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
    shown = " ".join(line.strip("│ ") for line in result.output.splitlines())
    assert "bad.bdf: not a readable BDF, EDF, FIF, BrainVision, EEGLAB or XDF" in " ".join(
        shown.split()
    )
    assert str(tmp_path) not in result.output
    assert not (out / "metrics.json").exists()


@pytest.mark.slow
def test_cli_calibrate_brainvision_with_a_rig_map_and_lab_labels(tmp_path) -> None:
    """A BrainAmp-like 500 Hz 8-channel .vhdr with device names and "hit"/"miss" comments."""
    import pybv

    from tests.eeg.caps import CAP_8, virtual_recording

    labels = [True, False] * 15
    raw = virtual_recording(500.0, CAP_8, labels=labels, seed=12)
    status = raw.get_data(picks="Status")[0]
    onsets = np.flatnonzero(np.diff(status, prepend=0) > 0)
    pybv.write_brainvision(
        data=raw.get_data(picks=CAP_8),
        sfreq=500.0,
        ch_names=[f"Ch{i + 1}" for i in range(8)],
        fname_base="s01",
        folder_out=tmp_path,
        events=[
            {"onset": int(s), "description": "hit" if ok else "miss", "type": "Comment"}
            for s, ok in zip(onsets, labels, strict=True)
        ],
    )
    rig = tmp_path / "rig.json"
    rig.write_text(json.dumps({f"Ch{i + 1}": ch for i, ch in enumerate(CAP_8)}))
    out = tmp_path / "model"
    args = ["eeg", "calibrate", str(tmp_path / "s01.vhdr"), "--out", str(out)]
    options = ["--max-passes", "1", "--no-report", "--no-onnx"]
    refused = runner.invoke(app, [*args, *options, "--event-label", "hit=correct"])
    assert refused.exit_code == 2
    assert "0 channels with standard 10-20/10-10" in " ".join(refused.output.split())
    bad = runner.invoke(app, [*args, "--channel-map", str(rig), "--event-label", "hit=ok"])
    assert bad.exit_code == 2 and "expected KEY=correct or KEY=error" in bad.output
    labelled = ["--event-label", "hit=correct", "--event-label", "miss=error"]
    result = runner.invoke(app, [*args, *options, "--channel-map", str(rig), *labelled])
    assert result.exit_code == 0, result.output
    config = json.loads((out / "classifier.json").read_text())
    assert (config["ch_names"], config["sfreq_in"]) == (CAP_8, 500.0)
    assert json.loads((out / "metrics.json").read_text())["n_epochs"] == 30
