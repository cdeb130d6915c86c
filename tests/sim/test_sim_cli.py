"""``bgrl sim ...`` and ``bgrl bench sim`` (tiny runs; the real figures come from the CLI)."""

from __future__ import annotations

import json
from pathlib import Path

from PIL import Image
from typer.testing import CliRunner

from services.cli.main import app

runner = CliRunner()


def test_map_png_draws_the_oracle_path(tmp_path: Path) -> None:
    out = tmp_path / "map.png"
    result = runner.invoke(app, ["sim", "map-png", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "oracle path" in result.output
    assert Image.open(out).mode == "RGB"
    bad = runner.invoke(app, ["sim", "map-png", "--out", str(out), "--map", "/nowhere.json"])
    assert bad.exit_code != 0
    assert "nowhere.json" in bad.output


def test_random_success_reports_a_rate(tmp_path: Path) -> None:
    out = tmp_path / "random.json"
    args = ["sim", "random-success", "--episodes", "5", "--task", "sssg", "--out", str(out)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads(out.read_text())
    assert summary["episodes"] == 5 and 0.0 <= summary["success_rate"] <= 1.0
    assert runner.invoke(app, ["sim", "random-success", "--task", "maze"]).exit_code != 0


def test_bench_sim_writes_json(tmp_path: Path) -> None:
    args = ["bench", "sim", "--out", str(tmp_path), "--env-steps", "200", "--rounds", "2"]
    args += ["--frames", "2", "--oracle-queries", "20", "--service-steps", "5"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "sim.json").read_text())
    env = report["env_step"]
    assert env["ratio_env_to_raycast"] == env["env_steps_per_s"] / env["raycast_batches_per_s"]
    assert report["render"]["camera_frame_shape"] == [240, 320, 3]
    assert report["oracle"]["build_cold_s"] > 0 and report["oracle"]["optimal_actions_us"] > 0
    assert report["service"]["http_step_ms"] > 0
    assert report["command"].startswith("bgrl bench sim --out")
