"""services.core: markers round-trip, settings validate, CLI assembles."""

from __future__ import annotations

import pytest
from pydantic import ValidationError
from typer.testing import CliRunner

from services.cli.main import app
from services.core.actions import TRIGGER_CORRECT, TRIGGER_ERROR, Action
from services.core.markers import ActionMarker
from services.core.settings import BaseServiceSettings


def test_marker_round_trip_and_trigger_codes() -> None:
    marker = ActionMarker(
        session_id="s1", step=3, episode=0, action=Action.TURN_LEFT, correct=False, timestamp=12.5
    )
    back = ActionMarker.from_lsl(marker.to_lsl())
    assert back == marker
    assert back.trigger == TRIGGER_ERROR
    assert marker.model_copy(update={"correct": True}).trigger == TRIGGER_CORRECT
    assert marker.model_copy(update={"correct": None}).trigger == 0


def test_marker_rejects_garbage() -> None:
    with pytest.raises(ValueError, match="not an action marker"):
        ActionMarker.from_lsl("hello")
    with pytest.raises(ValidationError):
        ActionMarker.from_lsl(
            '{"session_id": "s", "step": -1, "episode": 0, "action": 0, "timestamp": 1.0}'
        )


def test_settings_validate_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BGRL_PORT", "99999")
    with pytest.raises(ValidationError, match="port"):
        BaseServiceSettings()
    monkeypatch.setenv("BGRL_PORT", "8123")
    assert BaseServiceSettings().port == 8123


def test_cli_help_lists_commands() -> None:
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0, result.output
    assert "serve" in result.output
    assert "bench" in result.output
