"""HTTP access of the live-session runner to the sim, EEG and learner services.

Every call carries the internal service token. One retry rule (:func:`retry_while_down`):
exponential backoff (0.1 s doubling to 2 s) while the service is down, up to ``retry_s``;
then :class:`ServiceDownError` ends the job's attempt (the job is retried and resumes from
its rows). A call is repeated only when repeating it cannot do its work twice: when the
request never reached the service (connection refused or not made in time) or the service
answered 503, always; after a transport error once the request was sent (a timeout while
reading, a dropped connection) or a 502/504, only if the call is idempotent (GET, PUT,
DELETE, or a POST the caller marks ``idempotent=True`` because the service deduplicates
it). A sim step, reset or new session is not: its outcome is unknown, so the call raises
:class:`OutcomeUnknownError` (a :class:`ServiceDownError`) and the resumed attempt reads
what happened from the rows and the services. A 4xx answer is a :class:`ServiceCallError`
at once, with the service's detail.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, TypeVar

import httpx
from pydantic import Field

from services.worker.settings import WorkerSettings

logger = logging.getLogger(__name__)

RETRY_STATUSES = frozenset({502, 503, 504})
"""Answers of a service that is restarting (or of a proxy in front of it)."""
NOT_PROCESSED_STATUS = 503
"""The one restart answer that says the request was not processed."""
IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "OPTIONS", "PUT", "DELETE"})
NOT_SENT_ERRORS: tuple[type[httpx.TransportError], ...] = (httpx.ConnectError, httpx.ConnectTimeout)
"""Transport errors raised before the request reached the service."""
FIRST_BACKOFF_S = 0.1
MAX_BACKOFF_S = 2.0
T = TypeVar("T")


class LiveSettings(WorkerSettings):
    """Where the runner finds the services (``BGRL_SIM_URL``, ``BGRL_EEG_URL``,
    ``BGRL_LEARNER_URL``) and how long it waits for one that is down."""

    sim_url: str = Field("http://127.0.0.1:8001", description="The sim service.")
    eeg_url: str = Field("http://127.0.0.1:8002", description="The EEG service.")
    learner_url: str = Field("http://127.0.0.1:8003", description="The learner service.")
    live_retry_s: float = Field(
        60.0, gt=0, description="How long a live session waits for a service to come back."
    )


class ServiceDownError(RuntimeError):
    """A service stayed unreachable for the whole retry window."""


class OutcomeUnknownError(ServiceDownError):
    """A call that must not run twice failed after its request was sent: whether the service
    did it is unknown, so it is not repeated."""


class ServiceUnavailableError(RuntimeError):
    """One attempt found the service down (a retryable failure of :func:`retry_while_down`)."""


def retry_while_down(
    attempt: Callable[[], T],
    *,
    what: str,
    retry_s: float,
    retryable: Callable[[Exception], bool] = lambda exc: isinstance(exc, ServiceUnavailableError),
    on_retry: Callable[[], None] | None = None,
) -> T:
    """``attempt()``, repeated with exponential backoff while it raises an exception that
    ``retryable`` accepts, for at most ``retry_s`` seconds; then :class:`ServiceDownError`
    naming ``what`` and the last problem. Other exceptions propagate at once. ``on_retry``
    runs before each pause (a job checks for cancel there)."""
    deadline = time.monotonic() + retry_s
    backoff = FIRST_BACKOFF_S
    while True:
        try:
            return attempt()
        except Exception as exc:
            if not retryable(exc):
                raise
            problem = str(exc) or type(exc).__name__
            if time.monotonic() + backoff > deadline:
                raise ServiceDownError(f"{what} ({problem}) for {retry_s:g} s") from exc
        logger.warning("%s: %s; retrying", what, problem)
        if on_retry is not None:
            on_retry()
        time.sleep(backoff)
        backoff = min(backoff * 2, MAX_BACKOFF_S)


class ServiceCallError(RuntimeError):
    """A service refused a call (4xx/5xx other than the restart statuses)."""

    def __init__(self, service: str, status_code: int, detail: str) -> None:
        super().__init__(f"{service} answered {status_code}: {detail}")
        self.status_code = status_code
        self.detail = detail


class ServiceClient:
    """One service: ``call(method, path, json=...)`` -> decoded JSON (or None for 204)."""

    def __init__(
        self,
        name: str,
        base_url: str,
        token: str | None,
        *,
        retry_s: float,
        timeout_s: float = 30.0,
        on_retry: Callable[[], None] | None = None,
    ) -> None:
        self.name = name
        self.base_url = base_url.rstrip("/")
        self.headers = {"X-Service-Token": token} if token else {}
        self.retry_s = retry_s
        self.on_retry = on_retry
        self.retries = 0
        self._client = httpx.Client(base_url=self.base_url, headers=self.headers, timeout=timeout_s)

    def call(
        self,
        method: str,
        path: str,
        *,
        json: Any = None,
        params: Any = None,
        idempotent: bool | None = None,
    ) -> Any:
        """The service's decoded JSON answer (None for 204), retried while the service is
        down as the module says; ``idempotent`` (default: by the method) says whether a
        request that reached the service may be sent again."""
        repeatable = method.upper() in IDEMPOTENT_METHODS if idempotent is None else idempotent

        def attempt() -> Any:
            try:
                response = self._client.request(method, path, json=json, params=params)
            except NOT_SENT_ERRORS as exc:
                raise ServiceUnavailableError(f"{type(exc).__name__}: {exc}") from exc
            except httpx.TransportError as exc:
                if not repeatable:
                    raise self._unknown(method, path, f"{type(exc).__name__}: {exc}") from exc
                raise ServiceUnavailableError(f"{type(exc).__name__}: {exc}") from exc
            status = response.status_code
            if status in RETRY_STATUSES:
                if status != NOT_PROCESSED_STATUS and not repeatable:
                    raise self._unknown(method, path, f"HTTP {status}")
                raise ServiceUnavailableError(f"HTTP {status}")
            if status >= 400:
                try:
                    detail = str(response.json().get("detail"))
                except ValueError:
                    detail = response.text[:200]
                raise ServiceCallError(self.name, status, detail)
            return None if status == 204 else response.json()

        def counted_retry() -> None:
            self.retries += 1
            if self.on_retry is not None:
                self.on_retry()

        return retry_while_down(
            attempt,
            what=f"the {self.name} service at {self.base_url} is unreachable ({method} {path})",
            retry_s=self.retry_s,
            on_retry=counted_retry,
        )

    def _unknown(self, method: str, path: str, problem: str) -> OutcomeUnknownError:
        return OutcomeUnknownError(
            f"{self.name} {method} {path} failed after it was sent ({problem}); not repeated: "
            "it may have been done"
        )

    def call_once(self, method: str, path: str, *, json: Any = None) -> Any:
        """One attempt of :meth:`call`: no retry, any failure raises (``httpx.HTTPError`` or
        :class:`ServiceCallError`). For calls that only save time later, such as preparing
        a label."""
        response = self._client.request(method, path, json=json)
        if response.status_code >= 400:
            raise ServiceCallError(self.name, response.status_code, response.text[:200])
        return None if response.status_code == 204 else response.json()

    def close(self) -> None:
        self._client.close()


def clients(settings: LiveSettings, on_retry: Callable[[], None]) -> dict[str, ServiceClient]:
    """Clients of the sim, EEG and learner services."""
    token = settings.service_token
    return {
        name: ServiceClient(name, url, token, retry_s=settings.live_retry_s, on_retry=on_retry)
        for name, url in (
            ("sim", settings.sim_url),
            ("eeg", settings.eeg_url),
            ("learner", settings.learner_url),
        )
    }
