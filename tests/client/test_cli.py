"""``bgrl login``, ``bgrl jobs ...`` and ``bgrl models pull`` against the real api on loopback."""

from __future__ import annotations

import json
import stat
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from services.cli.main import app
from services.cli.platform import build_config
from services.client import PlatformClient
from tests.client.conftest import MODEL_BYTES, PASSWORD, STAFF_EMAIL, LiveApi

runner = CliRunner()


@pytest.fixture
def signed_in(live_api: LiveApi, credentials: Path) -> Iterator[Path]:
    """The CLI signed in as staff."""
    result = runner.invoke(
        app,
        ["login", "--url", live_api.url, "--email", STAFF_EMAIL, "--password-stdin"],
        input=PASSWORD + "\n",
    )
    assert result.exit_code == 0, result.output
    yield credentials


def bgrl(*args: str) -> tuple[int, str, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.stdout, result.stderr


def test_login_saves_an_api_token_readable_by_the_owner_only(
    live_api: LiveApi, signed_in: Path
) -> None:
    assert stat.S_IMODE(signed_in.stat().st_mode) == 0o600
    saved = json.loads(signed_in.read_text())
    assert (saved["api_url"], saved["email"]) == (live_api.url, STAFF_EMAIL)
    assert saved["token"].startswith("bgrl_")
    with PlatformClient(live_api.url) as client:
        assert client.login_with_api_token(saved["token"]).email == STAFF_EMAIL


def test_wrong_password_is_one_line(live_api: LiveApi, credentials: Path) -> None:
    result = runner.invoke(
        app,
        ["login", "--url", live_api.url, "--email", STAFF_EMAIL, "--password-stdin"],
        input="wrong-password\n",
    )
    assert result.exit_code == 1
    assert result.stderr == (
        "error: HTTP 401: wrong e-mail or password, or account deactivated (field password)\n"
    )
    assert not credentials.exists()


def test_not_signed_in(credentials: Path) -> None:
    code, out, err = bgrl("jobs", "list")
    assert (code, out) == (1, "")
    assert err == f"error: not signed in ({credentials} does not exist): run `bgrl login`\n"


def test_submit_list_wait_cancel(live_api: LiveApi, signed_in: Path, tmp_path: Path) -> None:
    config_file = tmp_path / "job.json"
    config_file.write_text(json.dumps({"task": "VSSG", "method": "rl_sparse"}))
    code, out, err = bgrl(
        "jobs", "submit", "guided_ppo", "--config", f"@{config_file}",
        "--set", "total_steps=2000", "--set", "ppo.n_epochs=4", "--set", "seed=7",
    )  # fmt: skip
    assert code == 0, err
    job_id = out.strip()
    assert err == f"submitted guided_ppo job {job_id} (queued)\n"
    token = json.loads(signed_in.read_text())["token"]
    with PlatformClient(live_api.url, token) as client:
        assert client.get_job(job_id).config == {
            "task": "vssg",
            "method": "rl_sparse",
            "seed": 7,
            "total_steps": 2000,
            "hf_treatment": "authors",
            "n_labels": 1000,
            "ppo": {"n_epochs": 4},
            "preset": "paper",
        }

    code, out, _ = bgrl("jobs", "list", "--status", "queued", "--limit", "500")
    assert code == 0
    listed = [line for line in out.splitlines() if line.startswith(job_id)]
    assert len(listed) == 1 and listed[0].split()[1:3] == ["guided_ppo", "queued"]
    assert listed[0].endswith("  VSSG rl_sparse seed 7, 2,000 steps")  # the kind's summary
    code, out, _ = bgrl("jobs", "list", "--json", "--limit", "1")
    assert (code, json.loads(out)["limit"]) == (0, 1)

    assert bgrl("jobs", "cancel", job_id)[:2] == (0, f"job {job_id}: cancelled\n")
    code, out, err = bgrl("jobs", "wait", job_id, "--poll", "0.1")
    assert (code, out, err) == (1, "", f"job {job_id} cancelled\n")  # one line, no bar

    code, out, _ = bgrl("jobs", "show", job_id[:6])
    assert code == 0
    assert out.splitlines()[:2] == [
        f"job       {job_id} (guided_ppo: VSSG rl_sparse seed 7, 2,000 steps)",
        "status    cancelled, 0%, 0 steps, attempt 0 of 3",
    ]
    assert '"total_steps": 2000' in out and "files     0 (none yet)" in out
    code, out, _ = bgrl("jobs", "show", job_id, "--json")
    assert (code, json.loads(out)["job"]["id"], json.loads(out)["files"]) == (0, job_id, [])
    code, out, _ = bgrl("jobs", "logs", job_id[:7])
    assert code == 0
    events = [line.split("  ", 1)[1] for line in out.splitlines()]
    assert events[0] == "submitted by staff@lab.test: kind guided_ppo"
    assert sorted(events[1:]) == ["cancel requested by staff@lab.test", "cancelled"]
    code, out, _ = bgrl("jobs", "logs", job_id, "--json")
    assert json.loads(out)["items"][0]["actor_email"] == "staff@lab.test"
    assert bgrl("jobs", "retry", job_id[:8])[:2] == (0, f"job {job_id}: queued again\n")
    assert bgrl("jobs", "cancel", job_id[:8])[0] == 0

    code, out, err = bgrl("jobs", "wait", "0123456789")
    assert (code, out) == (1, "")  # refused before any bar is drawn
    assert err == ("error: HTTP 404: no job with an id starting 0123456789 (field job_id)\n")
    code, _, err = bgrl("jobs", "cancel", job_id)
    assert (code, err) == (
        1,
        f"error: HTTP 409: job {job_id} is already cancelled (field job_id)\n",
    )


def test_submit_sets_the_stage2_method_and_the_preset(live_api: LiveApi, signed_in: Path) -> None:
    code, out, err = bgrl(
        "jobs", "submit", "guided_ppo", "--set", "task=sssg", "--set", "method=hf_sparse",
        "--set", "accuracy=0.7", "--set", "hf_method=noise_aware",
    )  # fmt: skip
    assert code == 0, err
    hf_job = out.strip()
    code, out, err = bgrl(
        "jobs", "submit", "reproduce", "--set", "quick=true", "--set", "preset=platform"
    )
    assert code == 0, err
    sweep = out.strip()
    token = json.loads(signed_in.read_text())["token"]
    with PlatformClient(live_api.url, token) as client:
        assert client.get_job(hf_job).config["hf_method"] == "noise_aware"
        assert client.get_job(sweep).config["preset"] == "platform"
    for job_id in (hf_job, sweep):
        assert bgrl("jobs", "cancel", job_id)[0] == 0
    code, _, err = bgrl(
        "jobs", "submit", "guided_ppo", "--set", "task=sssg", "--set", "method=rl_rich",
        "--set", "hf_method=paper",
    )  # fmt: skip
    assert (code, err) == (
        2,
        "error: HTTP 422: config.hf_method: hf_method applies to hf_sparse only, "
        "not rl_rich (field config.hf_method)\n",
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["jobs", "submit", "ppo"],
         "error: unknown job kind 'ppo'; use one of guided_ppo, reproduce, eeg_calibration, "
         "bids_export, session_replay\n"),
        (["jobs", "submit", "guided_ppo", "--config", "{task: sssg}"],
         "error: --config is not valid JSON: Expecting property name enclosed in double quotes "
         "at line 1 column 2\n"),
        (["jobs", "submit", "guided_ppo", "--config", "[1]"],
         "error: --config must be a JSON object, not list\n"),
        (["jobs", "submit", "guided_ppo", "--set", "seed"],
         "error: --set 'seed': expected KEY=VALUE (e.g. seed=3 or ppo.n_epochs=4)\n"),
        (["jobs", "submit", "guided_ppo", "--config", "@/nonexistent/job.json"],
         "error: --config: cannot read /nonexistent/job.json (No such file or directory)\n"),
        (["jobs", "submit", "guided_ppo", "--set", "task=sssg", "--set", "method=rl_sparse",
          "--set", "gamma=0.9"],
         "error: HTTP 422: config.gamma: Extra inputs are not permitted (field config.gamma)\n"),
        (["jobs", "list", "--status", "done"],
         "error: unknown status 'done'; use one of queued, running, succeeded, failed, "
         "cancelled\n"),
    ],
)  # fmt: skip
def test_bad_input_is_one_line_and_exit_2(signed_in: Path, args: list[str], message: str) -> None:
    code, out, err = bgrl(*args)
    assert (code, out, err) == (2, "", message)


def test_wait_and_pull_a_finished_job(live_api: LiveApi, signed_in: Path, tmp_path: Path) -> None:
    job_id, stored = live_api.finished_job_with_model()
    code, out, err = bgrl("jobs", "wait", job_id[:8])
    assert (code, out, err) == (0, f"job {job_id} succeeded\n", "")  # ended: no bar

    code, out, _ = bgrl("models", "pull", job_id[:8], "--out", str(tmp_path))
    target = tmp_path / f"policy-{job_id}.pt"
    assert code == 0
    assert target.read_bytes() == MODEL_BYTES
    assert out.startswith(f"saved {target} ({len(MODEL_BYTES)} bytes, sha256 ")

    stored.write_bytes(b"x" + MODEL_BYTES[1:])
    corrupt = tmp_path / "corrupt.pt"
    code, _, err = bgrl("models", "pull", job_id, "--out", str(corrupt))
    assert code == 1
    assert err.startswith(f"error: download of /api/v1/jobs/{job_id}/model is corrupt: sha256 ")
    assert not corrupt.exists()


def test_schedule_a_session_and_one_that_happened(live_api: LiveApi, signed_in: Path) -> None:
    """``bgrl sessions schedule`` by subject code; a start in the past is refused with the
    option that confirms it, and scheduled with it."""
    token = json.loads(signed_in.read_text())["token"]
    with PlatformClient(live_api.url, token) as client:
        subject = client.create_subject("S-CLI-SESSIONS")
    code, out, err = bgrl("sessions", "schedule", "S-CLI-SESSIONS", "test", "2037-12-07T09:00Z")
    assert code == 0, err
    session_id = int(out)
    assert err == (
        f"scheduled test session {session_id} of subject {subject.id} at 2037-12-07 09:00:00 "
        "UTC for 60 min\n"
    )
    code, out, err = bgrl("sessions", "schedule", str(subject.id), "rl", "2020-01-01T09:00Z")
    assert (code, out, err) == (
        2, "", "error: 2020-01-01T09:00:00+00:00 is in the past: add --allow-past to record a "
        "session that has happened\n",
    )  # fmt: skip
    code, out, _ = bgrl(
        "sessions", "schedule", str(subject.id), "rl", "2020-01-01T09:00Z", "--allow-past",
        "--json",
    )  # fmt: skip
    assert code == 0
    assert json.loads(out)["scheduled_at"] == "2020-01-01T09:00:00Z"
    code, out, _ = bgrl("sessions", "list", "--subject", "S-CLI-SESSIONS", "--json")
    starts = [s["scheduled_at"] for s in json.loads(out)["items"]]
    assert (code, starts) == (0, ["2020-01-01T09:00:00Z", "2037-12-07T09:00:00Z"])


def test_api_token_from_the_environment(
    live_api: LiveApi, credentials: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with PlatformClient(live_api.url) as client:
        client.login(STAFF_EMAIL, PASSWORD)
        token = client.create_api_token("ci").token
    assert token is not None
    monkeypatch.setenv("BGRL_API_TOKEN", token)
    monkeypatch.setenv("BGRL_API_URL", live_api.url)
    code, out, _ = bgrl("jobs", "list", "--json")
    assert code == 0
    assert json.loads(out)["offset"] == 0
    assert not credentials.exists()


def test_build_config_nests_and_parses_values() -> None:
    assert build_config('{"ppo": {"gamma": 0.9}}', ["ppo.n_epochs=4", "task=sssg", "x=[1, 2]"]) == {
        "ppo": {"gamma": 0.9, "n_epochs": 4},
        "task": "sssg",
        "x": [1, 2],
    }
    with pytest.raises(ValueError, match=r"--set 'task.x=1': task is not an object"):
        build_config(None, ["task=sssg", "task.x=1"])
