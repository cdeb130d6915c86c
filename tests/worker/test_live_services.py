"""The live runner's one retry rule: a call is repeated while the service is down, but a call
that must not run twice (a sim step, reset or new session) is never sent again once its
request may have reached the service."""

from __future__ import annotations

from collections.abc import Callable

import httpx
import pytest

from services.worker.live_services import (
    OutcomeUnknownError,
    ServiceCallError,
    ServiceClient,
    ServiceDownError,
)

Reply = Callable[[httpx.Request], httpx.Response]


def client(*replies: Reply, retry_s: float = 5.0) -> tuple[ServiceClient, list[str]]:
    """A sim client whose requests get ``replies`` in turn (the last one from then on); the
    paths of the requests that reached the transport."""
    seen: list[str] = []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(f"{request.method} {request.url.path}")
        return replies[min(len(seen), len(replies)) - 1](request)

    sim = ServiceClient("sim", "http://sim.test", "token", retry_s=retry_s)
    sim._client = httpx.Client(base_url=sim.base_url, transport=httpx.MockTransport(handler))
    return sim, seen


def raises(error: type[httpx.TransportError]) -> Reply:
    def reply(request: httpx.Request) -> httpx.Response:
        raise error("for the test", request=request)

    return reply


def answers(status: int, body: object = None) -> Reply:
    return lambda request: httpx.Response(status, json=body if body is not None else {})


def test_a_sim_step_is_not_sent_again_after_a_timeout_while_reading() -> None:
    sim, seen = client(raises(httpx.ReadTimeout), answers(200, {"ok": True}))
    with pytest.raises(OutcomeUnknownError, match=r"sim POST /sessions/s1/step failed after"):
        sim.call("POST", "/sessions/s1/step", json={"action": 0})
    assert seen == ["POST /sessions/s1/step"]  # once: the action may have been executed


@pytest.mark.parametrize("status", [502, 504])
def test_a_sim_step_is_not_sent_again_after_a_proxy_error(status: int) -> None:
    sim, seen = client(answers(status), answers(200, {"ok": True}))
    with pytest.raises(OutcomeUnknownError):
        sim.call("POST", "/sessions/s1/reset")
    assert len(seen) == 1


@pytest.mark.parametrize(
    "first", [raises(httpx.ConnectError), raises(httpx.ConnectTimeout), answers(503)]
)
def test_a_sim_step_that_never_reached_the_service_is_sent_again(first: Reply) -> None:
    sim, seen = client(first, answers(200, {"ok": True}))
    assert sim.call("POST", "/sessions/s1/step", json={"action": 1}) == {"ok": True}
    assert len(seen) == 2 and sim.retries == 1


@pytest.mark.parametrize("method", ["GET", "DELETE"])
def test_idempotent_calls_are_repeated_after_any_transport_error(method: str) -> None:
    sim, seen = client(raises(httpx.ReadTimeout), answers(502), answers(200, {"ok": True}))
    assert sim.call(method, "/sessions/s1") == {"ok": True}
    assert len(seen) == 3


def test_a_post_marked_idempotent_is_repeated() -> None:
    sim, seen = client(raises(httpx.RemoteProtocolError), answers(200, {"duplicate": True}))
    assert sim.call("POST", "/labels", json={}, idempotent=True) == {"duplicate": True}
    assert len(seen) == 2


def test_a_service_down_for_the_whole_window_ends_the_attempt_naming_it() -> None:
    sim, seen = client(raises(httpx.ConnectError), retry_s=0.5)
    with pytest.raises(ServiceDownError, match=r"the sim service at http://sim.test is unre"):
        sim.call("POST", "/sessions")
    assert 2 <= len(seen) <= 5  # backoff 0.1, 0.2, ... within 0.5 s


def test_a_refusal_is_not_retried() -> None:
    sim, seen = client(answers(422, {"detail": "action must be 0, 1 or 2"}))
    with pytest.raises(ServiceCallError, match="action must be 0, 1 or 2"):
        sim.call("POST", "/sessions/s1/step", json={"action": 7})
    assert len(seen) == 1
