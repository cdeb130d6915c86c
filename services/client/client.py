"""``PlatformClient``: the platform's REST api from a Python script (sync, on httpx).

Example::

    from services.client import PlatformClient
    from services.platform.jobs import GUIDED_PPO

    with PlatformClient("http://127.0.0.1:8000") as api:
        api.login("me@lab.org", "my password")
        job = api.submit_job(GUIDED_PPO.name, {"task": "sssg", "method": "hf_sparse",
                                               "accuracy": 0.7, "seed": 0, "total_steps": 40000})
        job = api.wait_job(job.id, timeout=3600, on_progress=lambda j: print(j.progress))
        api.download_model(job.id, "policy.pt")
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import os
import string
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, TypeVar

import httpx
from pydantic import BaseModel

from services.client.errors import (
    ChecksumMismatchError,
    PlatformError,
    WaitTimeoutError,
    error_from_response,
)
from services.client.schemas import (
    AccessToken,
    ApiToken,
    Artifact,
    Classifier,
    Curve,
    HFModel,
    Job,
    JobKind,
    JobLog,
    JobStatus,
    LabSession,
    Page,
    Subject,
    User,
)
from services.core.model_formats import ModelFormat

API = "/api/v1"
CHECKSUM_HEADER = "X-Checksum-Sha256"
DOWNLOAD_CHUNK_BYTES = 1024 * 1024

ModelT = TypeVar("ModelT", bound=BaseModel)
ProgressCallback = Callable[[Job], None]


@dataclass(frozen=True)
class DownloadedFile:
    """A file saved by a download, after its checksum was verified."""

    path: Path
    sha256: str
    size_bytes: int


def _query(**params: Any) -> dict[str, Any]:
    """Query parameters without the ones left at None."""
    return {key: value for key, value in params.items() if value is not None}


ID_CHARACTERS = frozenset(string.ascii_letters + string.digits + "_-")


def _segment(value: str, field: str) -> str:
    """A text id (a job's, an artifact's) as one path segment; :class:`PlatformError` for
    an empty one or one with other characters than letters, digits, ``_`` and ``-`` (which
    would address another route: ``/``, ``?``, ``#``, ``..``)."""
    if not value or not set(value) <= ID_CHARACTERS:
        raise PlatformError(f"{value!r} is not a valid id", field=field)
    return value


def _non_finite(value: Any, path: str = "") -> str | None:
    """The dotted path of the first NaN or infinity in a JSON body, None if there is none."""
    if isinstance(value, float) and not math.isfinite(value):
        return path or "body"
    if isinstance(value, Mapping):
        items: Any = value.items()
    elif isinstance(value, list | tuple):
        items = enumerate(value)
    else:
        return None
    for key, item in items:
        found = _non_finite(item, f"{path}.{key}" if path else str(key))
        if found is not None:
            return found
    return None


def _retry_after_s(response: httpx.Response) -> float | None:
    """The seconds a 503 answer asks to wait before the request is sent again (its
    ``Retry-After`` in seconds, at least 0.1), or None if it does not ask."""
    if response.status_code != 503:
        return None
    try:
        return max(0.1, float(response.headers["Retry-After"]))
    except (KeyError, ValueError):
        return None


class PlatformClient:
    """The platform api at ``base_url`` (e.g. ``http://127.0.0.1:8000``).

    ``token`` is an access token or API token (``bgrl_...``); without one, call
    :meth:`login` or :meth:`login_with_api_token` first. Every failed request raises
    :class:`PlatformError` with the HTTP status and the api's detail and field.

    A read (GET) answered 503 with ``Retry-After`` (the api's database restarting) is sent
    again after the wait the api asks for, for up to ``retry_s`` seconds; nothing else is
    repeated, as a write's outcome may be unknown.
    """

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        *,
        timeout_s: float = 30.0,
        retry_s: float = 60.0,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.retry_s = retry_s
        self._http = httpx.Client(base_url=self.base_url, timeout=timeout_s)

    def close(self) -> None:
        """Close the connections."""
        self._http.close()

    def __enter__(self) -> PlatformClient:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- transport ---------------------------------------------------------------------

    def _headers(self) -> dict[str, str]:
        if not self.token:
            return {}
        if not (self.token.isascii() and self.token.isprintable()) or " " in self.token:
            raise PlatformError(
                "the token is malformed: it has spaces, control or non-ASCII characters",
                field="token",
            )
        return {"Authorization": f"Bearer {self.token}"}

    def _send(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        body = kwargs.get("json")
        if body is not None and (where := _non_finite(body)) is not None:
            raise PlatformError(
                f"{where} is NaN or infinite, which JSON cannot carry; give a finite number",
                field=where,
            )
        deadline = time.monotonic() + self.retry_s
        while True:
            try:
                response = self._http.request(method, path, headers=self._headers(), **kwargs)
            except httpx.HTTPError as exc:
                raise PlatformError(f"cannot reach {self.base_url}: {exc}") from None
            if response.is_success:
                return response
            wait_s = _retry_after_s(response) if method == "GET" else None
            if wait_s is None or time.monotonic() + wait_s > deadline:
                raise error_from_response(response)
            time.sleep(wait_s)

    def _parse(self, response: httpx.Response, model: type[ModelT]) -> ModelT:
        """The answer as ``model``; :class:`PlatformError` if it is not what the api sends
        (e.g. a proxy's page, or another server at ``base_url``)."""
        try:
            return model.model_validate(response.json())
        except ValueError as exc:  # not JSON, or JSON of another shape
            summary = str(exc).splitlines()[0]
            raise PlatformError(
                f"unexpected answer from {response.request.url} (is {self.base_url} the "
                f"platform api?): {summary}",
                status=response.status_code,
            ) from None

    def _get(self, path: str, model: type[ModelT], **params: Any) -> ModelT:
        return self._parse(self._send("GET", path, params=_query(**params)), model)

    def _post(
        self, path: str, model: type[ModelT], body: Mapping[str, Any] | None = None
    ) -> ModelT:
        return self._parse(self._send("POST", path, json=body), model)

    # -- auth --------------------------------------------------------------------------

    def login(self, email: str, password: str) -> AccessToken:
        """Sign in with e-mail and password; later calls use the short-lived access token."""
        response = self._send(
            "POST", f"{API}/auth/token", data={"username": email, "password": password}
        )
        access = self._parse(response, AccessToken)
        self.token = access.access_token
        return access

    def login_with_api_token(self, token: str) -> User:
        """Use an API token (from :meth:`create_api_token` or ``bgrl login``); checks it
        by reading the account it belongs to, which is returned."""
        self.token = token
        try:
            return self.me()
        except PlatformError:
            self.token = None
            raise

    def me(self) -> User:
        """The signed-in account."""
        return self._get(f"{API}/users/me", User)

    def create_api_token(self, name: str, *, expires_in_days: int | None = 90) -> ApiToken:
        """A new API token acting as you; its ``token`` is returned this once only."""
        return self._post(
            f"{API}/tokens", ApiToken, {"name": name, "expires_in_days": expires_in_days}
        )

    def revoke_api_token(self, token_id: int) -> None:
        """Revoke one of your API tokens."""
        self._send("DELETE", f"{API}/tokens/{token_id}")

    # -- subjects and sessions -----------------------------------------------------------

    def create_subject(self, code: str, *, notes: str = "") -> Subject:
        """Register a subject by pseudonymous code (staff)."""
        return self._post(f"{API}/subjects", Subject, {"code": code, "notes": notes})

    def list_subjects(
        self, *, code: str | None = None, limit: int = 50, offset: int = 0
    ) -> Page[Subject]:
        """Subjects by code (``code``: codes starting with it)."""
        return self._get(f"{API}/subjects", Page[Subject], code=code, limit=limit, offset=offset)

    def get_subject(self, subject_id: int) -> Subject:
        """One subject."""
        return self._get(f"{API}/subjects/{subject_id}", Subject)

    def schedule_session(
        self,
        subject_id: int,
        kind: Literal["calibration", "test", "online", "rl"],
        scheduled_at: datetime,
        *,
        rig_id: int | None = None,
        duration_minutes: int = 60,
        notes: str = "",
        allow_past: bool = False,
    ) -> LabSession:
        """Schedule a session (``scheduled_at`` must carry a timezone); 409 on an overlap,
        422 at ``scheduled_at`` for a start in the past unless ``allow_past`` (a session that
        has happened)."""
        body = {
            "subject_id": subject_id,
            "kind": kind,
            "scheduled_at": scheduled_at.isoformat(),
            "rig_id": rig_id,
            "duration_minutes": duration_minutes,
            "notes": notes,
            "allow_past": allow_past,
        }
        return self._post(f"{API}/sessions", LabSession, body)

    def list_sessions(
        self,
        *,
        subject_id: int | None = None,
        status: str | None = None,
        day: str | None = None,
        week: str | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> Page[LabSession]:
        """Sessions in time order, by subject, status, day (YYYY-MM-DD) or ISO week."""
        return self._get(
            f"{API}/sessions",
            Page[LabSession],
            subject_id=subject_id,
            status=status,
            day=day,
            week=week,
            limit=limit,
            offset=offset,
        )

    def get_session(self, session_id: int) -> LabSession:
        """One session."""
        return self._get(f"{API}/sessions/{session_id}", LabSession)

    def cancel_session(self, session_id: int) -> LabSession:
        """Cancel a scheduled session."""
        return self._post(f"{API}/sessions/{session_id}/cancel", LabSession)

    # -- jobs --------------------------------------------------------------------------

    def submit_job(self, kind: JobKind, config: Mapping[str, Any]) -> Job:
        """Submit a job (staff); it is queued for the workers at once."""
        return self._post(f"{API}/jobs", Job, {"kind": kind, "config": dict(config)})

    def list_jobs(
        self,
        *,
        status: JobStatus | None = None,
        kind: str | None = None,
        submitter_id: int | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> Page[Job]:
        """Jobs, newest first."""
        return self._get(
            f"{API}/jobs",
            Page[Job],
            status=status,
            kind=kind,
            submitter_id=submitter_id,
            limit=limit,
            offset=offset,
        )

    def get_job(self, job_id: str) -> Job:
        """One job (``job_id``: the id, or a unique prefix of 6 or more characters)."""
        return self._get(f"{API}/jobs/{_segment(job_id, 'job_id')}", Job)

    def cancel_job(self, job_id: str) -> Job:
        """Cancel a job: a queued one at once, a running one within seconds."""
        return self._post(f"{API}/jobs/{_segment(job_id, 'job_id')}/cancel", Job)

    def retry_job(self, job_id: str) -> Job:
        """Run a failed or cancelled job again (it resumes from its last checkpoint)."""
        return self._post(f"{API}/jobs/{_segment(job_id, 'job_id')}/retry", Job)

    def job_log(self, job_id: str) -> JobLog:
        """The job's events, oldest first: who submitted, cancelled or retried it, when it
        started and how it ended."""
        return self._get(f"{API}/jobs/{_segment(job_id, 'job_id')}/log", JobLog)

    def job_curve(self, job_id: str) -> Curve:
        """The job's learning curve so far."""
        return self._get(f"{API}/jobs/{_segment(job_id, 'job_id')}/curve", Curve)

    def wait_job(
        self,
        job_id: str,
        *,
        timeout_s: float | None = None,
        on_progress: ProgressCallback | None = None,
        poll_s: float = 1.0,
    ) -> Job:
        """Poll the job until it succeeds, fails or is cancelled, and return it.

        ``on_progress(job)`` is called with the first state and then whenever the job
        changes. Raises :class:`WaitTimeoutError` after ``timeout_s`` (the job goes on).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        last_update: datetime | None = None
        while True:
            job = self.get_job(job_id)
            if on_progress is not None and job.updated_at != last_update:
                on_progress(job)
            last_update = job.updated_at
            if job.finished:
                return job
            if deadline is not None and time.monotonic() >= deadline:
                raise WaitTimeoutError(
                    f"job {job_id} still {job.status} after {timeout_s:g} s", field="job_id"
                )
            pause = poll_s if deadline is None else min(poll_s, deadline - time.monotonic())
            time.sleep(max(pause, 0.0))

    # -- models, classifiers and artifacts ------------------------------------------------

    def download_model(
        self,
        job_id: str,
        path: str | os.PathLike[str],
        *,
        model_format: ModelFormat = "torchscript",
    ) -> DownloadedFile:
        """Save a finished training job's policy (TorchScript, a torch.export program or ONNX,
        with its observation normalisation) to ``path``, verifying ``X-Checksum-Sha256``."""
        route = f"{API}/jobs/{_segment(job_id, 'job_id')}/model"
        return self._download(route, Path(path), format=model_format)

    def list_hf_models(
        self, *, task: str | None = None, limit: int = 50, offset: int = 0
    ) -> Page[HFModel]:
        """Human-feedback policies, newest first."""
        return self._get(f"{API}/hf-models", Page[HFModel], task=task, limit=limit, offset=offset)

    def get_hf_model(self, hf_model_id: int) -> HFModel:
        """One human-feedback policy and its metrics."""
        return self._get(f"{API}/hf-models/{hf_model_id}", HFModel)

    def download_hf_model(
        self,
        hf_model_id: int,
        path: str | os.PathLike[str],
        *,
        model_format: ModelFormat = "torchscript",
    ) -> DownloadedFile:
        """Save a human-feedback policy as TorchScript, a torch.export program (pt2) or ONNX,
        verifying its checksum."""
        return self._download(
            f"{API}/hf-models/{hf_model_id}/download", Path(path), format=model_format
        )

    def list_classifiers(
        self, *, subject_id: int | None = None, limit: int = 50, offset: int = 0
    ) -> Page[Classifier]:
        """ErrP classifiers, newest first."""
        return self._get(
            f"{API}/classifiers",
            Page[Classifier],
            subject_id=subject_id,
            limit=limit,
            offset=offset,
        )

    def download_classifier(
        self,
        classifier_id: int,
        path: str | os.PathLike[str],
        *,
        model_format: ModelFormat = "onnx",
    ) -> DownloadedFile:
        """Save an ErrP classifier as ONNX, TorchScript or a torch.export program (pt2),
        verifying its checksum."""
        return self._download(
            f"{API}/classifiers/{classifier_id}/download", Path(path), format=model_format
        )

    def list_artifacts(
        self,
        *,
        kind: str | None = None,
        job_id: str | None = None,
        limit: int = 50,
        offset: int = 0,
    ) -> Page[Artifact]:
        """Stored files, newest first, by kind or job."""
        return self._get(
            f"{API}/artifacts", Page[Artifact], kind=kind, job_id=job_id, limit=limit, offset=offset
        )

    def get_artifact(self, artifact_id: str) -> Artifact:
        """One stored file's record."""
        return self._get(f"{API}/artifacts/{_segment(artifact_id, 'artifact_id')}", Artifact)

    def download_artifact(self, artifact_id: str, path: str | os.PathLike[str]) -> DownloadedFile:
        """Save a stored file to ``path``, verifying its checksum."""
        route = f"{API}/artifacts/{_segment(artifact_id, 'artifact_id')}/download"
        return self._download(route, Path(path))

    def _download(self, route: str, path: Path, **params: Any) -> DownloadedFile:
        """Stream ``route`` into a temporary file next to ``path``, hashing as it goes; keep
        it as ``path`` only if the hash matches the ``X-Checksum-Sha256`` header."""
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.part")
        digest = hashlib.sha256()
        size = 0
        try:
            headers = self._headers()
            with self._http.stream(
                "GET", route, params=_query(**params), headers=headers
            ) as response:
                if not response.is_success:
                    response.read()
                    raise error_from_response(response)
                expected = response.headers.get(CHECKSUM_HEADER, "").strip().lower()
                if not expected:
                    raise PlatformError(f"the api sent no {CHECKSUM_HEADER} header for {route}")
                with partial.open("wb") as out:
                    for chunk in response.iter_bytes(DOWNLOAD_CHUNK_BYTES):
                        digest.update(chunk)
                        size += len(chunk)
                        out.write(chunk)
                    out.flush()
                    os.fsync(out.fileno())
        except httpx.HTTPError as exc:
            partial.unlink(missing_ok=True)
            raise PlatformError(f"download from {self.base_url}{route} failed: {exc}") from None
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
        got = digest.hexdigest()
        if got != expected:
            partial.unlink(missing_ok=True)
            raise ChecksumMismatchError(
                f"download of {route} is corrupt: sha256 {got}, the api announced {expected}; "
                f"{path} was not written"
            )
        with contextlib.suppress(OSError):
            partial.chmod(0o644)
        partial.replace(path)
        return DownloadedFile(path=path, sha256=got, size_bytes=size)
