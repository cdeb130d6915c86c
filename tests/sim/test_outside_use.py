"""The sim as outside code uses it: the env under gymnasium's wrappers, vector envs, copies
and a closed env; the service with map names no file can have and one session stepped from
many threads."""

from __future__ import annotations

import copy
import pickle
import subprocess
import sys
import threading
import warnings
from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.error import ClosedEnvironmentError
from gymnasium.wrappers import FlattenObservation, NormalizeObservation, RecordEpisodeStatistics

import services.sim  # noqa: F401  (registers the ids)
from services.sim.app import create_app
from services.sim.env import BrainNavEnv
from services.sim.settings import SimSettings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # starlette asks for httpx2; httpx works
    from fastapi.testclient import TestClient


# --------------------------------------------------------------------------- the env


def test_a_negative_render_size_is_a_value_error_not_a_dead_process() -> None:
    """pybullet aborted the whole interpreter (std::bad_alloc) when asked for such a frame."""
    code = (
        "import services.sim.env as e\n"
        "try:\n"
        "    env = e.BrainNavEnv(render_mode='rgb_array', render_width=-5)\n"
        "    env.reset(seed=0)\n"
        "    env.render()\n"
        "except ValueError as exc:\n"
        "    print('refused:', exc)\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "refused: render_width must be an integer in [1, 4096] pixels, got -5" in done.stdout


@pytest.mark.parametrize(
    ("keyword", "size"), [("render_width", 0), ("render_height", 320.5), ("render_width", True)]
)
def test_render_sizes_must_be_positive_integers(keyword: str, size: object) -> None:
    with pytest.raises(ValueError, match=f"{keyword} must be an integer"):
        BrainNavEnv(render_mode="rgb_array", **{keyword: size})


def test_a_closed_env_says_so_on_step_reset_and_render() -> None:
    env = gym.make("services.sim:BrainNav-SSSG-v0", render_mode="rgb_array")
    env.reset(seed=0)
    env.close()
    env.close()  # a second close does nothing
    core = env.unwrapped
    for call, what in (
        (lambda: core.step(0), "step"),
        (core.reset, "reset"),
        (core.render, "render"),
    ):
        with pytest.raises(
            ClosedEnvironmentError, match=f"cannot {what}: this BrainNavEnv was closed"
        ):
            call()


def test_a_copy_is_refused_and_cannot_end_the_original() -> None:
    """A deep copy shared the original's pybullet client: closing it broke the original."""
    env = BrainNavEnv()
    try:
        env.reset(seed=0)
        for make_copy in (copy.deepcopy, copy.copy, pickle.dumps):
            with pytest.raises(TypeError, match="cannot be copied or pickled"):
                make_copy(env)
        _, reward, terminated, _, _ = env.step(0)  # the original still works
        assert (reward, terminated) == (-1.0, False)
    finally:
        env.close()


def test_gymnasium_wrappers_and_seeded_reproducibility() -> None:
    env = NormalizeObservation(
        FlattenObservation(RecordEpisodeStatistics(gym.make("services.sim:BrainNav-VSSG-v0")))
    )
    try:
        env.reset(seed=4)
        env.action_space.seed(4)
        for _ in range(200):
            obs, _, terminated, truncated, info = env.step(env.action_space.sample())
            assert obs.shape == (13,) and np.all(np.isfinite(obs))
            if terminated or truncated:
                break
        assert info["episode"]["l"] >= 1 and info["episode"]["r"] <= -1
    finally:
        env.close()
    # same seed, same actions: the same trajectory, also from a fresh env
    runs = []
    for _ in range(2):
        with gym.make("services.sim:BrainNav-VSSG-v0") as plain:
            obs, _ = plain.reset(seed=11)
            runs.append([obs, *(plain.step(a)[0] for a in (0, 1, 0, 2, 0))])
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))


def test_async_vector_env_matches_the_sync_one() -> None:
    actions = np.array([[0, 1], [0, 0], [2, 0], [0, 0]])
    results = []
    for mode in ("sync", "async"):
        envs = gym.make_vec("services.sim:BrainNav-VSSG-v0", num_envs=2, vectorization_mode=mode)
        try:
            obs, _ = envs.reset(seed=[5, 6])
            steps = [obs, *(envs.step(a)[0] for a in actions)]
        finally:
            envs.close()
        envs.close()  # closing twice is harmless
        results.append(np.stack(steps))
    assert np.array_equal(results[0], results[1])


# --------------------------------------------------------------------------- the service


@pytest.fixture(scope="module")
def client() -> Iterator[TestClient]:
    settings = SimSettings(lsl_markers=False, max_sessions=3, log_level="WARNING")
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


@pytest.mark.parametrize("name", ["bad\u0000name", "~no-such-user-bgrl/default.json"])
def test_a_map_name_no_file_can_have_is_a_422_naming_map(client: TestClient, name: str) -> None:
    """A NUL byte (ValueError) or an unknown user's home (RuntimeError) was a bare 500."""
    before = len(client.get("/sessions").json())
    response = client.post("/sessions", json={"map": name})
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["field"] == "map" and body["detail"].startswith("unknown map ")
    assert len(client.get("/sessions").json()) == before


def test_one_session_stepped_from_many_threads_counts_every_action_once(
    client: TestClient,
) -> None:
    sid = client.post("/sessions", json={"seed": 0}).json()["id"]
    try:
        statuses: list[int] = []
        steps: list[int] = []
        lock = threading.Lock()

        def stepper() -> None:
            for _ in range(6):
                response = client.post(f"/sessions/{sid}/step", json={"action": 1})
                with lock:
                    statuses.append(response.status_code)
                    if response.status_code == 200:
                        steps.append(response.json()["marker"]["step"])

        threads = [threading.Thread(target=stepper) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert statuses == [200] * 24  # turning in place never ends the episode
        assert sorted(steps) == list(range(24))
        state = client.get(f"/sessions/{sid}").json()
        assert state["step"] == state["episode_step"] == 24
        markers = client.get(f"/sessions/{sid}/markers").json()
        assert [m["step"] for m in markers] == list(range(24))
    finally:
        client.delete(f"/sessions/{sid}")


def test_a_close_reason_fits_a_websocket_close_frame(client: TestClient) -> None:
    """The reason was cut at 120 characters: 240 bytes for a non-ASCII id, beyond the 123
    bytes a close frame can carry (a protocol error in the server instead of close 4404)."""
    session_id = "\u00e9" * 100
    with client.websocket_connect(f"/sessions/{session_id}/stream") as ws:
        assert ws.receive_json()["detail"] == f"no session with id {session_id!r}"
        closing = ws.receive()
    assert closing["code"] == 4404
    reason = closing["reason"].encode()
    assert 100 < len(reason) <= 123
    assert reason.decode().startswith("no session with id '\u00e9")
