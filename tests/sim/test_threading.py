"""Sessions under concurrent use: parallel creation, listeners outside the session lock."""

from __future__ import annotations

import os
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor

import pytest

from services.core.actions import Action
from services.sim.app import create_app
from services.sim.errors import PacedModeError
from services.sim.registry import resolve_map
from services.sim.sessions import PacedPolicy, SimSession
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient


def test_concurrent_session_creation_keeps_stdout(capfd: pytest.CaptureFixture) -> None:
    settings = SimSettings(lsl_markers=False, max_sessions=6)
    with TestClient(create_app(settings)) as client:
        barrier = threading.Barrier(6)

        def open_one(seed: int) -> int:
            barrier.wait()
            return client.post("/sessions", json={"seed": seed, "task": "vssg"}).status_code

        with ThreadPoolExecutor(6) as pool:
            codes = list(pool.map(open_one, range(6)))
        assert codes == [201] * 6
        assert client.get("/health").json()["sessions"] == 6
        refused = client.post("/sessions", json={})
        assert refused.status_code == 409 and refused.json()["detail"].startswith("6 sessions")
    capfd.readouterr()
    os.write(1, b"stdout still works\n")
    os.write(2, b"stderr too\n")
    assert capfd.readouterr() == ("stdout still works\n", "stderr too\n")


def _session() -> SimSession:
    name, path, nav_map = resolve_map(None)
    return SimSession(
        "s1",
        task="sssg",
        reward_mode="sparse",
        map_name=name,
        map_path=path,
        nav_map=nav_map,
        seed=0,
        publisher=None,
    )


def lock_free_in_listener(session: SimSession) -> tuple[list[bool], object]:
    """A listener that checks, from another thread, that the session's lock is free."""
    seen: list[bool] = []

    def try_lock() -> None:
        acquired = session._lock.acquire(timeout=1)
        if acquired:
            session._lock.release()
        seen.append(acquired)

    def listener() -> None:
        probe = threading.Thread(target=try_lock)
        probe.start()
        probe.join()

    return seen, listener


def test_listeners_run_outside_the_session_lock() -> None:
    session = _session()
    try:
        seen, listener = lock_free_in_listener(session)
        session.add_listener(listener)
        session.step(1)
        session.reset(3)
        assert seen == [True, True]
        # paced mode: steps and the auto-reset notify outside the lock as well
        session.start_paced(PacedPolicy.ORACLE, period_s=0.05, max_actions=25)
        deadline = time.monotonic() + 10
        while session.paced_status().running and time.monotonic() < deadline:
            time.sleep(0.02)
        status = session.paced_status()
        assert status.error is None and status.actions_executed == 25
        assert session.episode == 2  # the oracle reached the goal, the paced mode reset once
        assert seen == [True] * (2 + 25 + 1)
    finally:
        session.close()


def test_notifying_under_the_lock_is_refused() -> None:
    session = _session()
    try:
        with session._lock, pytest.raises(RuntimeError, match="outside the session's lock"):
            session._notify()
    finally:
        session.close()


def test_manual_steps_and_resets_are_refused_in_the_lock_hold_that_would_run_them() -> None:
    """The refusal while the paced mode runs is part of ``step``/``reset`` (one lock hold),
    not a separate check a paced mode starting in between could slip past: the session's
    own methods refuse, and a step blocked on the lock when the paced mode starts is refused."""
    session = _session()
    try:
        session.start_paced(PacedPolicy.QUEUE, period_s=60.0)
        with pytest.raises(PacedModeError):
            session.step(Action.FORWARD)
        with pytest.raises(PacedModeError):
            session.reset()
        session.stop_paced()
        outcomes: list[object] = []

        def manual_step() -> None:
            try:
                outcomes.append(session.step(Action.FORWARD))
            except PacedModeError as exc:
                outcomes.append(exc)

        with session._lock:  # the step waits for the lock while the paced mode starts
            stepper = threading.Thread(target=manual_step)
            stepper.start()
            time.sleep(0.2)
            session.start_paced(PacedPolicy.QUEUE, period_s=60.0)
        stepper.join(5)
        assert len(outcomes) == 1 and isinstance(outcomes[0], PacedModeError)
        assert session.step_count == 0
    finally:
        session.close()
