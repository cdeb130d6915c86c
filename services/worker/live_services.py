"""HTTP access of the live-session runner to the sim, EEG and learner services.

Every call carries the internal service token and is retried with exponential backoff while
the service is unreachable or answers 502/503/504 (it is restarting), up to ``retry_s``;
then :class:`ServiceDownError` ends the job's attempt (the job is retried and resumes from
its rows). A 4xx answer is a :class:`ServiceCallError` at once, with the service's detail.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import httpx
from pydantic import Field

from services.worker.settings import WorkerSettings

logger = logging.getLogger(__name__)

RETRY_STATUSES = frozenset({502, 503, 504})
FIRST_BACKOFF_S = 0.1
MAX_BACKOFF_S = 2.0


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

    def call(self, method: str, path: str, *, json: Any = None, params: Any = None) -> Any:
        deadline = time.monotonic() + self.retry_s
        backoff = FIRST_BACKOFF_S
        while True:
            try:
                response = self._client.request(method, path, json=json, params=params)
            except httpx.TransportError as exc:
                problem = f"{type(exc).__name__}: {exc}"
            else:
                if response.status_code not in RETRY_STATUSES:
                    if response.status_code >= 400:
                        try:
                            detail = str(response.json().get("detail"))
                        except ValueError:
                            detail = response.text[:200]
                        raise ServiceCallError(self.name, response.status_code, detail)
                    return None if response.status_code == 204 else response.json()
                problem = f"HTTP {response.status_code}"
            if time.monotonic() + backoff > deadline:
                raise ServiceDownError(
                    f"the {self.name} service at {self.base_url} is unreachable ({problem}) "
                    f"for {self.retry_s:g} s"
                )
            self.retries += 1
            logger.warning("%s %s %s: %s; retrying", self.name, method, path, problem)
            if self.on_retry is not None:
                self.on_retry()
            time.sleep(backoff)
            backoff = min(backoff * 2, MAX_BACKOFF_S)

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
