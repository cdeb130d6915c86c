"""``bgrl eeg information --first-seed``: which virtual subjects are measured."""

from __future__ import annotations

import json
from typing import Any

import pytest
from typer.testing import CliRunner

from services.cli.main import app


def _row(seed: int, target: float) -> dict[str, Any]:
    """A row with the fields ``summarize`` reads (the measurement itself is not under test)."""
    return {
        "seed": seed,
        "target_accuracy": target,
        "target_reached": True,
        "accuracy": target,
        "subject_quality": 0.1,
        "hard_bits_bsc": 0.03,
        "hard_information": 0.03,
        "soft_information": 0.04,
        "soft_information_ci": [0.035, 0.045],
        "gaussian_reference_hard": 0.03,
        "gaussian_reference_soft": 0.045,
        "variability": {
            "errp_mean_uv": -3.0,
            "errp_cv": 0.2,
            "background_sd_uv": 10.0,
            "single_trial_snr": 0.1,
        },
    }


@pytest.mark.parametrize(
    ("extra", "expected"), [([], [0, 1, 2]), (["--first-seed", "1000"], [1000, 1001, 1002])]
)
def test_information_measures_the_subjects_from_the_first_seed(
    tmp_path, monkeypatch, extra: list[str], expected: list[int]
) -> None:
    import services.worker.label_information as label_information

    measured: list[int] = []

    def fake_measure(seed: int, targets: list[float], config: Any, **_: Any) -> list[dict]:
        measured.append(seed)
        return [_row(seed, t) for t in targets]

    monkeypatch.setattr(label_information, "measure_subject", fake_measure)
    out = tmp_path / "information"
    args = ["eeg", "information", "--out", str(out), "--targets", "0.6", "--seeds", "3", *extra]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert measured == expected
    rows = json.loads((out / "information.json").read_text())["rows"]
    assert [r["seed"] for r in rows] == expected


def test_information_refuses_a_negative_first_seed(tmp_path) -> None:
    args = ["eeg", "information", "--out", str(tmp_path / "x"), "--first-seed", "-1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2
