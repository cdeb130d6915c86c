"""``bgrl user``: the first admin from the command line, then a login through the api."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from services.api.app import create_app
from services.cli.main import app as cli
from tests.api.conftest import login, make_settings


def test_user_create_admin_then_login(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    data = tmp_path / "data"
    monkeypatch.setenv("BGRL_DATA_DIR", str(data))
    runner = CliRunner()
    created = runner.invoke(
        cli, ["user", "create", "Boss@Lab.org", "--admin", "--password", "p" * 12]
    )
    assert created.exit_code == 0, created.output
    assert created.output == "created admin boss@lab.org (id 1)\n"
    again = runner.invoke(cli, ["user", "create", "boss@lab.org", "--password", "p" * 12])
    assert again.exit_code == 1
    assert "a user with e-mail boss@lab.org exists" in again.output
    weak = runner.invoke(cli, ["user", "set-password", "boss@lab.org", "--password", "short"])
    assert weak.exit_code == 1
    listed = runner.invoke(cli, ["user", "list"])
    assert listed.output == "1\tboss@lab.org\tadmin\tactive\n"
    # the api finds the admin: no first-start account is made, the CLI's password works
    settings = make_settings(
        data, f"sqlite:///{data / 'bgrl.db'}", admin_email=None, admin_password=None
    )
    with TestClient(create_app(settings)) as client:
        headers = login(client, "boss@lab.org", "p" * 12)
        users = client.get("/api/v1/users", headers=headers).json()
    assert [u["email"] for u in users["items"]] == ["boss@lab.org"]
