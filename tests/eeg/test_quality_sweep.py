"""``bgrl eeg quality-sweep`` on two tiny SYNTHETIC subjects: every decoder on each split,
the JSON, CSV and plot."""

from __future__ import annotations

import csv
import json

from typer.testing import CliRunner

from services.cli.main import app
from services.eeg.decoding.calibration import DECODERS


def test_quality_sweep_writes_every_decoder_to_json_csv_and_png(tmp_path) -> None:
    args = ["eeg", "quality-sweep", "--out", str(tmp_path), "--seeds", "2", "--actions", "60"]
    args += ["--max-passes", "2", "--quality", "0", "--quality", "1"]
    done = CliRunner().invoke(app, args)
    assert done.exit_code == 0, done.output
    result = json.loads((tmp_path / "quality_sweep.json").read_text())
    assert result["decoders"] == list(DECODERS) and result["synthetic"] is True
    assert len(result["runs"]) == 4  # 2 subjects x 2 levels
    for run in result["runs"]:
        assert set(run["decoders"]) == set(DECODERS) and run["decoder"] in DECODERS
        kept = run["decoders"][run["decoder"]]
        assert run["test_accuracy"] == kept["test_accuracy"]
        assert kept["val_accuracy"] == max(d["val_accuracy"] for d in run["decoders"].values())
    for entry in result["summary"]:
        assert entry["n_seeds"] == 2 and sum(entry["kept"].values()) == 2
    with (tmp_path / "quality_sweep.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [(r["quality"], r["decoder"]) for r in rows] == [
        (q, d) for q in ("0.0", "1.0") for d in (*DECODERS, "kept")
    ]
    assert (tmp_path / "quality_sweep.png").stat().st_size > 20_000
    assert "xdawn_rg test acc." in done.output
