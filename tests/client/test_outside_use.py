"""The client and the ``bgrl`` CLI used carelessly: numbers JSON cannot carry, ids that are
not ids, tokens with odd characters, downloads to where nothing can be written, answers
that are not the api's. Each must be a :class:`PlatformError` (CLI: one ``error:`` line and
a non-zero exit), never a traceback."""

from __future__ import annotations

import math
import typing
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI
from fastapi.responses import HTMLResponse
from typer.main import get_command
from typer.testing import CliRunner, Result

from services.cli.main import app
from services.client import PlatformClient, PlatformError
from services.client.schemas import JobKind
from services.platform.jobs import SUBMITTED_KINDS
from tests.client.conftest import PASSWORD, STAFF_EMAIL, LiveApi
from tests.helpers import serve_in_thread

runner = CliRunner()


def _login(url: str) -> Result:
    return runner.invoke(
        app, ["login", "--url", url, "--email", STAFF_EMAIL, "--password-stdin"], input=PASSWORD
    )


@pytest.fixture
def signed_in(live_api: LiveApi, credentials: Path) -> Iterator[Path]:
    """The CLI signed in as staff."""
    result = _login(live_api.url)
    assert result.exit_code == 0, result.output
    yield credentials


def _one_line_error(result: Result, code: int) -> str:
    """The CLI's error line, after checking it failed cleanly with ``code``."""
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(
        result.exception
    )
    assert result.exit_code == code, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.mark.parametrize(
    "args",
    [
        ["--set", "accuracy=NaN"],
        ["--set", "accuracy=Infinity"],
        ["--set", "accuracy=1e400"],
        ["--config", '{"accuracy": -Infinity}'],
        ["--config", '{"accuracy": 1e999}'],
    ],
)
def test_a_number_json_cannot_carry_is_one_line(signed_in: Path, args: list[str]) -> None:
    """Was a ValueError traceback from the JSON encoder, after the config was parsed."""
    base = ["jobs", "submit", "guided_ppo", "--set", "task=sssg", "--set", "method=hf_sparse"]
    line = _one_line_error(runner.invoke(app, [*base, *args]), 2)
    assert "accuracy" in line or "--config" in line
    assert "number" in line


def test_the_client_refuses_nan_naming_the_field(staff: PlatformClient) -> None:
    config = {"task": "sssg", "method": "hf_sparse", "accuracy": math.nan}
    with pytest.raises(PlatformError) as caught:
        staff.submit_job("guided_ppo", config)
    assert caught.value.field == "config.accuracy"
    assert "NaN or infinite" in caught.value.detail
    assert staff.list_jobs().total == 0


@pytest.mark.parametrize("job_id", ["", "abc/../../subjects", "a b?c#d", ".."])
def test_an_id_that_is_not_an_id_is_refused_by_the_client(
    staff: PlatformClient, job_id: str, tmp_path: Path
) -> None:
    """``""`` reached the job list (a 307 read as a job: a JSONDecodeError traceback);
    ``/``, ``?`` and ``#`` addressed other routes (a confusing 404 or 405)."""
    for call in (
        lambda: staff.get_job(job_id),
        lambda: staff.cancel_job(job_id),
        lambda: staff.download_model(job_id, tmp_path / "policy.pt"),
        lambda: staff.get_artifact(job_id),
    ):
        with pytest.raises(PlatformError) as caught:
            call()
        assert caught.value.field in ("job_id", "artifact_id")
        assert "is not a valid id" in caught.value.detail
    assert not (tmp_path / "policy.pt").exists()


@pytest.mark.parametrize("command", [["jobs", "wait"], ["jobs", "cancel"]])
def test_the_cli_with_an_empty_job_id_is_one_line(signed_in: Path, command: list[str]) -> None:
    line = _one_line_error(runner.invoke(app, [*command, ""]), 1)
    assert line == "error: '' is not a valid id (field job_id)"


def test_pull_to_a_place_that_cannot_be_written_is_one_line(
    live_api: LiveApi, signed_in: Path, tmp_path: Path
) -> None:
    """Was a FileNotFoundError / NotADirectoryError traceback."""
    job_id, _ = live_api.finished_job_with_model()
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    result = runner.invoke(app, ["models", "pull", job_id, "--out", str(blocker / "policy.pt")])
    line = _one_line_error(result, 1)
    assert str(blocker) in line


def test_a_token_with_non_ascii_characters_is_one_line(
    live_api: LiveApi, credentials: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Was a UnicodeEncodeError traceback from the header encoding."""
    monkeypatch.setenv("BGRL_API_TOKEN", "bgrl_\u00e9t\u00e9")
    line = _one_line_error(runner.invoke(app, ["jobs", "list", "--url", live_api.url]), 1)
    assert line.endswith("(field token)")
    with PlatformClient(live_api.url) as client, pytest.raises(PlatformError) as caught:
        client.login_with_api_token("bgrl_ line\nbreak")
    assert caught.value.field == "token"
    assert client.token is None


def test_every_job_kind_of_the_api_can_be_submitted_and_listed(signed_in: Path) -> None:
    """The client knew three of the api's five kinds: `bgrl jobs submit bids_export` was
    refused by the CLI itself."""
    assert typing.get_args(JobKind) == SUBMITTED_KINDS
    result = runner.invoke(app, ["jobs", "submit", "bids_export", "--set", "subject_id=999999"])
    line = _one_line_error(result, 2)
    assert line == "error: HTTP 422: no subject with id 999999 (field config.subject_id)"
    listed = runner.invoke(app, ["jobs", "list", "--kind", "session_replay"])
    assert listed.exit_code == 0, listed.output
    unknown = _one_line_error(runner.invoke(app, ["jobs", "list", "--kind", "bogus"]), 2)
    assert unknown.startswith("error: unknown job kind 'bogus'; use one of guided_ppo, ")


def test_login_that_cannot_save_its_token_leaves_no_token_behind(
    live_api: LiveApi, credentials: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Was an OSError traceback, with the API token just created left valid on the api."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("BGRL_CREDENTIALS_FILE", str(blocker / "credentials.json"))
    with PlatformClient(live_api.url) as client:
        client.login(STAFF_EMAIL, PASSWORD)

        def tokens() -> dict[int, str | None]:
            page = client._send("GET", "/api/v1/tokens", params={"limit": 500}).json()
            return {token["id"]: token["revoked_at"] for token in page["items"]}

        before = tokens()
        line = _one_line_error(_login(live_api.url), 1)
        assert f"cannot save the credentials to {blocker / 'credentials.json'}" in line
        created = {i: revoked for i, revoked in tokens().items() if i not in before}
    assert len(created) == 1, "the login created one token"
    assert all(revoked is not None for revoked in created.values())


def test_an_answer_that_is_not_the_apis_is_a_platform_error(tmp_path: Path) -> None:
    """A URL pointing at another web server (or a proxy's page): the client raised
    JSONDecodeError / pydantic's ValidationError, the CLI showed a traceback."""
    other = FastAPI()

    @other.get("/{path:path}")
    def page(path: str) -> HTMLResponse:
        return HTMLResponse("<html>a login portal</html>")

    with serve_in_thread(other) as url, PlatformClient(url, "bgrl_token") as client:
        with pytest.raises(PlatformError) as caught:
            client.get_job("0123abcd")
        assert caught.value.status == 200
        assert "unexpected answer from" in caught.value.detail
        assert "the platform api?" in caught.value.detail
        with pytest.raises(PlatformError):
            client.login("me@lab.test", "password")


def test_help_of_every_command_works() -> None:
    """Already right: ``--help`` of every command and subcommand exits 0 with its usage."""
    paths: list[list[str]] = []

    def walk(command: object, path: list[str]) -> None:
        paths.append(path)
        for name, sub in getattr(command, "commands", {}).items():
            walk(sub, [*path, name])

    walk(get_command(app), [])
    assert len(paths) > 30
    for path in paths:
        result = runner.invoke(app, [*path, "--help"])
        assert result.exit_code == 0, (path, result.output)
        assert "Usage:" in result.output
