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
    create = ["user", "create", "Boss@Lab.org", "--admin", "--password", "p" * 12]
    created = runner.invoke(cli, [*create, "--create-database"])
    assert created.exit_code == 0, created.output
    assert created.stdout == "created admin boss@lab.org (id 1)\n"
    assert created.stderr == f"database: sqlite:///{data / 'bgrl.db'}\n"
    again = runner.invoke(cli, ["user", "create", "boss@lab.org", "--password", "p" * 12])
    assert again.exit_code == 1
    assert "a user with e-mail boss@lab.org exists" in again.output
    weak = runner.invoke(cli, ["user", "set-password", "boss@lab.org", "--password", "short"])
    assert weak.exit_code == 1
    listed = runner.invoke(cli, ["user", "list"])
    assert listed.stdout == "1\tboss@lab.org\tadmin\tactive\n"
    # the api finds the admin: no first-start account is made, the CLI's password works
    settings = make_settings(
        data, f"sqlite:///{data / 'bgrl.db'}", admin_email=None, admin_password=None
    )
    with TestClient(create_app(settings)) as client:
        headers = login(client, "boss@lab.org", "p" * 12)
        users = client.get("/api/v1/users", headers=headers).json()
    assert [u["email"] for u in users["items"]] == ["boss@lab.org"]


def test_user_commands_refuse_a_missing_database_unless_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Run from the wrong folder, `bgrl user list` used to make an empty ./data/bgrl.db."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("BGRL_DATA_DIR", raising=False)
    monkeypatch.delenv("BGRL_DATABASE_URL", raising=False)
    runner = CliRunner()
    where = tmp_path / "data" / "bgrl.db"
    for args in (
        ["user", "list"],
        ["user", "set-password", "a@lab.org", "--password", "p" * 12],
        ["user", "create", "a@lab.org", "--password", "p" * 12],
    ):
        refused = runner.invoke(cli, args)
        assert refused.exit_code == 1, refused.output
        assert refused.stdout == ""
        assert f"error: no platform database at sqlite:///{where}: set BGRL_DATA_DIR" in (
            refused.stderr
        )
        assert "--create-database" in refused.stderr
        assert not (tmp_path / "data").exists()
    # an empty file (or a database without the platform's tables) is no platform database
    (tmp_path / "data").mkdir()
    where.touch()
    assert runner.invoke(cli, ["user", "list"]).exit_code == 1
    made = runner.invoke(cli, ["user", "create", "a@lab.org", "--password", "p" * 12,
                               "--create-database"])  # fmt: skip
    assert made.exit_code == 0, made.output
    assert runner.invoke(cli, ["user", "list"]).stdout == "1\ta@lab.org\tstaff\tactive\n"
