"""``bgrl demo --accelerated``: the whole loop in one command (services, calibration,
classifier, online session, guided PPO and RL-sparse from the same seed) at a tiny size. Its
summary says what a lab reads off it: pi_HF's SPL, the label channel the session used, the
decoded accuracy and the steps each run needed to SPL 0.7."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from services.cli.main import app


@pytest.fixture
def environment_kept() -> Iterator[None]:
    """The demo points this process's BGRL_* variables at the services it starts (as the
    command's own process would): put them back for the tests after it."""
    saved = dict(os.environ)
    yield
    os.environ.clear()
    os.environ.update(saved)


@pytest.mark.usefixtures("environment_kept")
def test_the_accelerated_demo_reports_the_guided_run_beside_rl_sparse(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    result = CliRunner().invoke(app, [
        "demo", "--accelerated", "--out", str(out), "--calibration-actions", "60",
        "--labels", "12", "--total-steps", "256", "--max-passes", "5", "--quality", "1.0",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["synthetic"] is True and summary["labels"] == 12
    assert summary["label_channel"] == "soft"  # the calibrated classifier's default
    assert 0.0 <= summary["live_decoding_accuracy"] <= 1.0
    assert 0.0 <= summary["hf_policy_spl"] <= 1.0
    assert summary["steps"] == 256 and summary["rl_sparse_final_spl"] is not None
    assert {"guided_steps_to_0_7", "rl_sparse_steps_to_0_7"} <= summary.keys()
    assert (out / "demo.png").stat().st_size > 0
