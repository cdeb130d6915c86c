"""``bgrl login``, ``bgrl jobs ...``, ``bgrl sessions ...``, ``bgrl models pull``: the
platform api from a shell."""

from __future__ import annotations

import json
import math
import socket
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn, get_args

import typer

from services.client import Job, PlatformClient, PlatformError
from services.client.config import (
    DEFAULT_API_URL,
    ClientSettings,
    Credentials,
    CredentialsError,
    load_credentials,
    save_credentials,
)
from services.client.schemas import JobStatus
from services.core.model_formats import SUFFIXES, ModelFormat
from services.core.settings import SettingsError, load_settings
from services.platform.jobs import KIND_NAMES, SUBMITTED_KINDS

jobs_app = typer.Typer(
    help="Submit, follow, inspect, cancel and retry jobs on the platform.", no_args_is_help=True
)
models_app = typer.Typer(help="Download trained models.", no_args_is_help=True)
sessions_app = typer.Typer(help="Schedule and list lab sessions.", no_args_is_help=True)

UrlOption = Annotated[
    str | None,
    typer.Option(
        "--url",
        help=f"Base URL of the api (default: BGRL_API_URL, the URL saved by "
        f"`bgrl login`, else {DEFAULT_API_URL}).",
    ),
]
JobIdArgument = Annotated[
    str, typer.Argument(help="The job's id, or a unique prefix of it (6 characters or more).")
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print the answer as JSON.")]


EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


def _fail(message: str, code: int = EXIT_FAILED) -> NoReturn:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code)


def _settings() -> ClientSettings:
    try:
        return load_settings(ClientSettings)
    except SettingsError as exc:
        _fail(str(exc), EXIT_BAD_INPUT)


@contextmanager
def _client(url: str | None) -> Iterator[PlatformClient]:
    """A client signed in with BGRL_API_TOKEN or the saved credentials; API errors become
    one line on stderr (exit 2 for refused input, 1 otherwise)."""
    settings = _settings()
    token = settings.api_token.get_secret_value() if settings.api_token else None
    saved_url = None
    if token is None:
        try:
            saved = load_credentials(settings.credentials_file)
        except CredentialsError as exc:
            _fail(str(exc))
        token, saved_url = saved.token, saved.api_url
    base_url = url or settings.api_url or saved_url or DEFAULT_API_URL
    try:
        with PlatformClient(base_url, token) as client:
            yield client
    except PlatformError as exc:
        _fail(str(exc), EXIT_BAD_INPUT if exc.is_bad_input else EXIT_FAILED)
    except OSError as exc:  # a local file: e.g. where a download is saved
        where = f"{exc.filename}: " if exc.filename else ""
        _fail(f"{where}{exc.strerror or exc}")


def login(
    url: UrlOption = None,
    email: Annotated[str | None, typer.Option(help="Your account's e-mail (prompted).")] = None,
    password_stdin: Annotated[
        bool, typer.Option(help="Read the password from the first line of stdin.")
    ] = False,
    token: Annotated[
        str | None, typer.Option(help="Save this existing API token instead of signing in.")
    ] = None,
    days: Annotated[
        int, typer.Option(min=1, max=3650, help="Lifetime of the API token created.")
    ] = 90,
) -> None:
    """Sign in and save an API token for later commands (mode 600, BGRL_CREDENTIALS_FILE,
    default ~/.config/bgrl/credentials.json)."""
    settings = _settings()
    base_url = url or settings.api_url or DEFAULT_API_URL
    try:
        with PlatformClient(base_url) as client:
            if token is not None:
                user = client.login_with_api_token(token)
                saved = Credentials(api_url=base_url, email=user.email, token=token)
                expires = "as issued"
            else:
                email = email or typer.prompt("e-mail")
                if password_stdin:
                    password = sys.stdin.readline().rstrip("\n")
                else:
                    password = typer.prompt("password", hide_input=True)
                client.login(email, password)
                name = f"bgrl cli on {socket.gethostname()}"[:100]
                created = client.create_api_token(name, expires_in_days=days)
                assert created.token is not None
                user = client.me()
                saved = Credentials(
                    api_url=base_url, email=user.email, token=created.token, token_id=created.id
                )
                expires = f"until {created.expires_at:%Y-%m-%d}" if created.expires_at else ""
            try:
                save_credentials(settings.credentials_file, saved)
            except OSError as exc:
                if saved.token_id is not None:  # a token not kept is not left valid either
                    client.revoke_api_token(saved.token_id)
                _fail(
                    f"cannot save the credentials to {settings.credentials_file} "
                    f"({exc.strerror or exc}); set BGRL_CREDENTIALS_FILE to a writable path"
                )
    except PlatformError as exc:
        _fail(str(exc), EXIT_BAD_INPUT if exc.is_bad_input else EXIT_FAILED)
    typer.echo(
        f"signed in to {base_url} as {user.email} ({user.role}); API token ({expires}) saved "
        f"to {settings.credentials_file}"
    )


class NotJsonNumberError(ValueError):
    """A number the api's JSON cannot carry: NaN, Infinity, or one too large for a float."""


def _refuse_constant(name: str) -> Any:
    raise NotJsonNumberError(f"{name} is not a number JSON can carry")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise NotJsonNumberError(f"{text} is out of range for a number")
    return value


def _loads(text: str) -> Any:
    """JSON as the api reads it: no NaN, Infinity or numbers too large for a float."""
    return json.loads(text, parse_constant=_refuse_constant, parse_float=_finite_float)


def _parse_value(text: str) -> Any:
    """``--set`` values: JSON when they parse as JSON (numbers, true, lists...), else text."""
    try:
        return _loads(text)
    except NotJsonNumberError:
        raise
    except ValueError:
        return text


def build_config(config: str | None, assignments: list[str]) -> dict[str, Any]:
    """The job config from ``--config JSON|@file`` and ``--set key=value`` (dotted keys nest,
    e.g. ``ppo.n_epochs=4``); ValueError with one line on bad input."""
    values: dict[str, Any] = {}
    if config is not None:
        source = "--config"
        text = config
        if config.startswith("@"):
            source = config[1:]
            try:
                text = Path(source).read_text(encoding="utf-8")
            except OSError as exc:
                raise ValueError(f"--config: cannot read {source} ({exc.strerror})") from None
            except UnicodeDecodeError:
                raise ValueError(f"--config: {source} is not UTF-8 text") from None
        try:
            parsed = _loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(
                f"{source} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
            ) from None
        except ValueError as exc:
            raise ValueError(f"{source} is not valid JSON: {exc}") from None
        if not isinstance(parsed, dict):
            raise ValueError(f"{source} must be a JSON object, not {type(parsed).__name__}")
        values = parsed
    for item in assignments:
        key, sep, raw = item.partition("=")
        parts = key.strip().split(".")
        if not sep or not all(parts):
            raise ValueError(f"--set {item!r}: expected KEY=VALUE (e.g. seed=3 or ppo.n_epochs=4)")
        target = values
        for part in parts[:-1]:
            child = target.setdefault(part, {})
            if not isinstance(child, dict):
                raise ValueError(f"--set {item!r}: {part} is not an object in the config")
            target = child
        try:
            target[parts[-1]] = _parse_value(raw.strip())
        except NotJsonNumberError as exc:
            raise ValueError(f"--set {item!r}: {exc}") from None
    return values


def submit(
    kind: Annotated[str, typer.Argument(help=f"Job kind: {', '.join(SUBMITTED_KINDS)}.")],
    config: Annotated[
        str | None, typer.Option(help="The config as JSON, or @FILE holding it.")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="KEY=VALUE config entry (repeatable; ppo.n_epochs=4 nests)."),
    ] = None,
    url: UrlOption = None,
) -> None:
    """Submit a job; prints its id (e.g. JOB=$(bgrl jobs submit guided_ppo --set ...))."""
    if kind not in SUBMITTED_KINDS:
        _fail(f"unknown job kind {kind!r}; use one of {', '.join(SUBMITTED_KINDS)}", EXIT_BAD_INPUT)
    try:
        values = build_config(config, set_ or [])
    except ValueError as exc:
        _fail(str(exc), EXIT_BAD_INPUT)
    with _client(url) as client:
        job = client.submit_job(kind, values)  # type: ignore[arg-type]
    typer.echo(f"submitted {job.kind} job {job.id} ({job.status})", err=True)
    typer.echo(job.id)


def _age(moment: datetime | None) -> str:
    if moment is None:
        return "-"
    return moment.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S")


def list_jobs(
    status: Annotated[
        str | None, typer.Option(help=f"Only jobs in: {', '.join(get_args(JobStatus))}.")
    ] = None,
    kind: Annotated[str | None, typer.Option(help="Only jobs of this kind.")] = None,
    limit: Annotated[int, typer.Option(min=1, max=500, help="Jobs shown (newest first).")] = 20,
    as_json: JsonOption = False,
    url: UrlOption = None,
) -> None:
    """The newest jobs: id, kind, status, progress, created."""
    if status is not None and status not in get_args(JobStatus):
        _fail(
            f"unknown status {status!r}; use one of {', '.join(get_args(JobStatus))}",
            EXIT_BAD_INPUT,
        )
    if kind is not None and kind not in KIND_NAMES:
        _fail(f"unknown job kind {kind!r}; use one of {', '.join(KIND_NAMES)}", EXIT_BAD_INPUT)
    with _client(url) as client:
        page = client.list_jobs(status=status, kind=kind, limit=limit)  # type: ignore[arg-type]
    if as_json:
        typer.echo(page.model_dump_json(indent=2))
        return
    typer.echo(
        f"{'id':<32}  {'kind':<15}  {'status':<9}  {'progress':>8}  {'created (UTC)':<19}  what"
    )
    for job in page.items:
        typer.echo(
            f"{job.id:<32}  {job.kind:<15}  {job.status:<9}  {job.progress:>8.0%}  "
            f"{_age(job.created_at):<19}  {job.summary}"
        )
    typer.echo(f"{len(page.items)} of {page.total} job(s)", err=True)


def show(job_id: JobIdArgument, as_json: JsonOption = False, url: UrlOption = None) -> None:
    """A job: status, progress, attempts, error, config and its stored files."""
    with _client(url) as client:
        job = client.get_job(job_id)
        files = client.list_artifacts(job_id=job.id, limit=500)
    if as_json:
        typer.echo(
            json.dumps(
                {
                    "job": job.model_dump(mode="json"),
                    "files": [f.model_dump(mode="json") for f in files.items],
                },
                indent=2,
            )
        )
        return
    lines = [
        f"job       {job.id} ({job.kind}: {job.summary})",
        f"status    {job.status}, {job.progress:.0%}, {job.steps_done} steps, attempt "
        f"{job.attempts} of {job.max_attempts}"
        + ("" if job.resumed_from_step is None else f", resumed from step {job.resumed_from_step}"),
        f"submitted {_age(job.created_at)} UTC; started {_age(job.started_at)}; "
        f"finished {_age(job.finished_at)}",
    ]
    if job.parent_id:
        lines.append(f"run of    {job.parent_id}")
    if job.error:
        lines.append(f"error     {job.error}")
    lines.append("config    " + json.dumps(job.config, sort_keys=True))
    lines.append(f"files     {files.total}" + ("" if files.items else " (none yet)"))
    for stored in files.items:
        best = " (the job's model)" if stored.id == job.model_artifact_id else ""
        lines.append(
            f"  {stored.id}  {stored.kind:<10} {stored.size_bytes:>10} B  "
            f"{stored.relpath.rsplit('/', 1)[-1]}{best}"
        )
    typer.echo("\n".join(lines))


def logs(job_id: JobIdArgument, as_json: JsonOption = False, url: UrlOption = None) -> None:
    """A job's events, oldest first: who submitted, cancelled or retried it, when it started
    (attempt, resumed step) and how it ended (the error)."""
    with _client(url) as client:
        log = client.job_log(job_id)
    if as_json:
        typer.echo(log.model_dump_json(indent=2))
        return
    for entry in log.items:
        who = f" by {entry.actor_email}" if entry.actor_email else ""
        detail = f": {entry.detail}" if entry.detail else ""
        typer.echo(f"{_age(entry.at)} UTC  {entry.event}{who}{detail}")


def retry(job_id: JobIdArgument, url: UrlOption = None) -> None:
    """Run a failed or cancelled job again (it resumes from its last checkpoint)."""
    with _client(url) as client:
        job = client.retry_job(job_id)
    typer.echo(f"job {job.id}: {job.status} again")


def _describe(job: Job) -> str:
    text = f"job {job.id} {job.status}"
    if job.status == "failed" and job.error:
        text += f": {job.error}"
    if job.resumed_from_step is not None:
        text += f" (resumed from step {job.resumed_from_step})"
    return text


def wait(
    job_id: JobIdArgument,
    timeout: Annotated[
        float | None, typer.Option(min=0, help="Give up after this many seconds.")
    ] = None,
    poll: Annotated[float, typer.Option(min=0.1, help="Seconds between checks.")] = 1.0,
    url: UrlOption = None,
) -> None:
    """Follow a job with a progress bar until it ends, then print one line saying how it
    ended; exit 0 only if it succeeded. An unknown id is refused before any bar is drawn."""
    from tqdm import tqdm

    with _client(url) as client:
        job = client.get_job(job_id)  # a 404 here: no bar
        if not job.finished:
            with tqdm(
                total=100,
                desc=job.id[:8],
                unit="%",
                leave=False,  # the line below says how it ended
                bar_format="{l_bar}{bar}| {n:.0f}% [{elapsed}{postfix}]",
            ) as bar:

                def on_progress(job: Job) -> None:
                    bar.n = round(100 * job.progress, 1)
                    bar.set_postfix_str(f"{job.status}, {job.steps_done} steps", refresh=False)
                    bar.refresh()

                job = client.wait_job(
                    job.id, timeout_s=timeout, on_progress=on_progress, poll_s=poll
                )
    typer.echo(_describe(job), err=job.status != "succeeded")
    if job.status != "succeeded":
        raise typer.Exit(EXIT_FAILED)


def cancel(job_id: JobIdArgument, url: UrlOption = None) -> None:
    """Cancel a job: a queued one at once, a running one within seconds."""
    with _client(url) as client:
        job = client.cancel_job(job_id)
    state = "cancelled" if job.status == "cancelled" else "cancel requested"
    typer.echo(f"job {job.id}: {state}")


def pull(
    job_id: Annotated[
        str,
        typer.Argument(help="A finished guided_ppo job's id, or a unique prefix (6 or more)."),
    ],
    out: Annotated[
        Path, typer.Option(help="Where to save the policy (a folder: policy-<job id>.<ending>).")
    ],
    model_format: Annotated[
        ModelFormat,
        typer.Option(
            "--format",
            help="torchscript (.pt, torch.jit.load), pt2 (torch.export.load) or onnx "
            "(onnxruntime); each holds the observation normalisation.",
        ),
    ] = "torchscript",
    url: UrlOption = None,
) -> None:
    """Download a job's trained policy, verifying its SHA-256 (a corrupt file is not kept)."""
    with _client(url) as client:
        job = client.get_job(job_id)
        if out.is_dir():
            out = out / f"policy-{job.id}{SUFFIXES[model_format]}"
        saved = client.download_model(job.id, out, model_format=model_format)
    typer.echo(f"saved {saved.path} ({saved.size_bytes} bytes, sha256 {saved.sha256})")


SessionKind = Literal["calibration", "test", "online", "rl"]


def _start(text: str) -> datetime:
    """An ISO 8601 start; one without a timezone is in this machine's local time."""
    try:
        start = datetime.fromisoformat(text)
    except ValueError:
        _fail(
            f"START {text!r} is not an ISO 8601 date and time (e.g. 2027-01-18T09:30)",
            EXIT_BAD_INPUT,
        )
    return start if start.tzinfo is not None else start.astimezone()


def _subject_id(client: PlatformClient, subject: str) -> int:
    """A subject given by id or by its code."""
    if subject.isdigit():
        return int(subject)
    for found in client.list_subjects(code=subject, limit=50).items:
        if found.code == subject:
            return found.id
    _fail(f"no subject with code {subject!r}", EXIT_BAD_INPUT)


def schedule(
    subject: Annotated[str, typer.Argument(help="The subject's code or id.")],
    kind: Annotated[SessionKind, typer.Argument(help="calibration, test, online or rl.")],
    start: Annotated[
        str,
        typer.Argument(
            help="Start, ISO 8601 (2027-01-18T09:30; without a timezone: this machine's)."
        ),
    ],
    minutes: Annotated[int, typer.Option(min=1, max=1440, help="Duration.")] = 60,
    rig: Annotated[int | None, typer.Option(help="The rig's id.")] = None,
    notes: Annotated[str, typer.Option(help="Notes.")] = "",
    allow_past: Annotated[
        bool,
        typer.Option(
            "--allow-past", help="Schedule it even though it starts in the past (it happened)."
        ),
    ] = False,
    as_json: JsonOption = False,
    url: UrlOption = None,
) -> None:
    """Schedule a lab session; prints its id. A start in the past is refused unless
    --allow-past; an overlap with the subject's or the rig's sessions is refused."""
    when = _start(start)
    with _client(url) as client:
        subject_id = _subject_id(client, subject)
        try:
            session = client.schedule_session(
                subject_id, kind, when, rig_id=rig, duration_minutes=minutes, notes=notes,
                allow_past=allow_past,
            )  # fmt: skip
        except PlatformError as exc:
            if exc.field == "scheduled_at" and "allow_past" in exc.detail:
                _fail(
                    f"{when.isoformat()} is in the past: add --allow-past to record a session "
                    "that has happened",
                    EXIT_BAD_INPUT,
                )
            raise
    if as_json:
        typer.echo(session.model_dump_json(indent=2))
        return
    typer.echo(
        f"scheduled {session.kind} session {session.id} of subject {subject_id} at "
        f"{_age(session.scheduled_at)} UTC for {session.duration_minutes} min",
        err=True,
    )
    typer.echo(session.id)


def list_sessions(
    subject: Annotated[str | None, typer.Option(help="Only this subject's (code or id).")] = None,
    week: Annotated[str | None, typer.Option(help="Only this ISO week (2027-W03).")] = None,
    limit: Annotated[int, typer.Option(min=1, max=500, help="Sessions shown.")] = 50,
    as_json: JsonOption = False,
    url: UrlOption = None,
) -> None:
    """Sessions in time order: id, subject, kind, status, start (UTC), minutes."""
    with _client(url) as client:
        subject_id = _subject_id(client, subject) if subject is not None else None
        page = client.list_sessions(subject_id=subject_id, week=week, limit=limit)
    if as_json:
        typer.echo(page.model_dump_json(indent=2))
        return
    typer.echo(f"{'id':>6}  {'subject':>7}  {'kind':<11}  {'status':<9}  start (UTC)          min")
    for s in page.items:
        typer.echo(
            f"{s.id:>6}  {s.subject_id:>7}  {s.kind:<11}  {s.status:<9}  "
            f"{_age(s.scheduled_at)}  {s.duration_minutes:>3}"
        )
    typer.echo(f"{len(page.items)} of {page.total} session(s)", err=True)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``login``, ``jobs``, ``sessions`` and ``models``."""
    app.command("login")(login)
    jobs_app.command("submit")(submit)
    jobs_app.command("list")(list_jobs)
    jobs_app.command("show")(show)
    jobs_app.command("logs")(logs)
    jobs_app.command("retry")(retry)
    jobs_app.command("wait")(wait)
    jobs_app.command("cancel")(cancel)
    models_app.command("pull")(pull)
    sessions_app.command("schedule")(schedule)
    sessions_app.command("list")(list_sessions)
    app.add_typer(jobs_app, name="jobs")
    app.add_typer(sessions_app, name="sessions")
    app.add_typer(models_app, name="models")
