"""pybullet without noise: the quiet import, the Husky built from shapes, clients released."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pybullet_data
import pytest

from services.sim import bullet, world
from services.sim.bullet import pybullet
from services.sim.env import BrainNavEnv
from services.sim.maps import MapError
from services.sim.world import RayMemo


def _frames(client: int, robot: int) -> np.ndarray:
    pybullet.resetBasePositionAndOrientation(
        robot,
        [0.3, 0.2, 0.0],
        pybullet.getQuaternionFromEuler([0.0, 0.0, 0.5]),
        physicsClientId=client,
    )
    frames = []
    for eye in ([-3.0, 0.0, 2.6], [2.0, 2.0, 1.0], [0.0, -3.0, 1.5]):
        view = pybullet.computeViewMatrix(eye, [0.3, 0.2, 0.2], [0.0, 0.0, 1.0])
        proj = pybullet.computeProjectionMatrixFOV(60.0, 4.0 / 3.0, 0.1, 40.0)
        _, _, rgba, _, _ = pybullet.getCameraImage(
            320, 240, view, proj, renderer=pybullet.ER_TINY_RENDERER, physicsClientId=client
        )
        frames.append(np.asarray(rgba, dtype=np.uint8).reshape(240, 320, 4))
    return np.stack(frames)


def test_husky_from_shapes_renders_exactly_like_the_urdf(capfd: pytest.CaptureFixture) -> None:
    urdf_client = bullet.connect()
    try:
        pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=urdf_client)
        robot = pybullet.loadURDF(
            "husky/husky.urdf", useFixedBase=True, physicsClientId=urdf_client
        )
        from_urdf = _frames(urdf_client, robot)
    finally:
        bullet.disconnect(urdf_client)
    assert "No inertial data" in capfd.readouterr().out  # the noise the URDF importer makes
    client = bullet.connect()
    try:
        from_shapes = _frames(client, bullet.add_husky(client))
    finally:
        bullet.disconnect(client)
    assert capfd.readouterr() == ("", "")  # building it from shapes says nothing
    assert (from_shapes[..., :3] != 255).any()  # the robot is in view
    np.testing.assert_array_equal(from_shapes, from_urdf)


def test_importing_and_using_the_env_prints_nothing(tmp_path) -> None:
    room = tmp_path / "room.json"  # a small map: its oracle builds in milliseconds
    room.write_text(
        '{"name": "room", "bounds": {"x_max": 4, "y_max": 3}, '
        '"start": {"x": 1, "y": 1.5}, "goal": {"x": 3.2, "y": 1.5}}'
    )
    workdir = tmp_path / "work"
    workdir.mkdir()
    code = (
        "import gymnasium as gym, services.sim\n"
        f"env = gym.make('services.sim:BrainNav-SSSG-v0', map_path={str(room)!r}, "
        "render_mode='rgb_array')\n"
        "env.reset(seed=0); env.step(0); env.render(); env.close()\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=workdir, check=True
    )
    assert (out.stdout, out.stderr) == ("", "")
    assert list(workdir.iterdir()) == []  # and writes nothing to the working directory


def test_env_construction_leaves_stdout_alone(capfd: pytest.CaptureFixture) -> None:
    before = os.fstat(1).st_ino
    env = BrainNavEnv()
    env.close()
    os.write(1, b"still here\n")
    assert os.fstat(1).st_ino == before
    assert capfd.readouterr().out == "still here\n"


def test_only_an_env_that_renders_builds_the_husky(monkeypatch: pytest.MonkeyPatch) -> None:
    """The Husky is visual only (rays never hit it) and its meshes cost ~9 MB of a ~36 MB
    env: a headless env (training, sweeps) goes without it and sees the same rays."""
    built: list[int] = []
    real = bullet.add_husky
    monkeypatch.setattr(bullet, "add_husky", lambda client: built.append(client) or real(client))
    headless, rendering = BrainNavEnv(), BrainNavEnv(render_mode="rgb_array")
    try:
        assert built == [rendering._client]
        obs_a, _ = headless.reset(seed=3)
        obs_b, _ = rendering.reset(seed=3)
        assert np.array_equal(obs_a, obs_b)
        for action in [0, 0, 1, 0, 2, 0, 0]:
            assert np.array_equal(headless.step(action)[0], rendering.step(action)[0])
        assert headless.render() is None and rendering.render().shape[2] == 3
    finally:
        headless.close()
        rendering.close()


def test_headless_envs_of_a_map_share_one_world_with_the_same_rays() -> None:
    """Each headless env's rays in the shared world equal a private world's (an env that
    renders), step for step, with the other headless envs moving in between."""
    shared = [BrainNavEnv(task="vssg") for _ in range(3)]
    private = [BrainNavEnv(task="vssg", render_mode="rgb_array") for _ in range(3)]
    try:
        assert len({env._client for env in shared}) == 1
        assert len({env._client for env in private}) == 3
        for seed, (a, b) in enumerate(zip(shared, private, strict=True)):
            assert np.array_equal(a.reset(seed=seed)[0], b.reset(seed=seed)[0])
        rng = np.random.default_rng(0)
        for _ in range(60):
            for a, b in zip(shared, private, strict=True):
                action = int(rng.integers(3))
                obs_a, _, done_a, _, _ = a.step(action)
                obs_b, _, done_b, _, _ = b.step(action)
                assert np.array_equal(obs_a, obs_b) and done_a == done_b
                if done_a:
                    assert np.array_equal(a.reset()[0], b.reset()[0])
    finally:
        for env in shared + private:
            env.close()


def test_remembered_rays_equal_cast_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    """Rays remembered per pose (a memo emptied every 7 poses here) give the observations
    of rays cast at every step, with fewer casts."""

    class Forgetful(RayMemo):
        def remember(self, pose: tuple[float, float, int], rays: tuple[float, ...]) -> None:
            pass

    casts: dict[int, int] = {}  # client -> rayTestBatch calls
    cast = pybullet.rayTestBatch

    def counted(*args, physicsClientId: int):
        casts[physicsClientId] = casts.get(physicsClientId, 0) + 1
        return cast(*args, physicsClientId=physicsClientId)

    monkeypatch.setattr(world, "RAY_MEMO_MAX_POSES", 7)
    monkeypatch.setattr(pybullet, "rayTestBatch", counted)
    remembering = BrainNavEnv(task="sssg")
    casting = BrainNavEnv(task="sssg", render_mode="rgb_array")
    casting._ray_memo = Forgetful()
    try:
        rng = np.random.default_rng(1)
        for episode in range(4):
            assert np.array_equal(
                remembering.reset(seed=episode)[0], casting.reset(seed=episode)[0]
            )
            for _ in range(40):  # turns back and forth revisit poses
                action = int(rng.choice([0, 1, 2, 1, 2]))
                obs_a, reward_a, done_a, _, _ = remembering.step(action)
                obs_b, reward_b, done_b, _, _ = casting.step(action)
                assert np.array_equal(obs_a, obs_b) and (reward_a, done_a) == (reward_b, done_b)
                if done_a:
                    break
        assert len(remembering._ray_memo) <= 7
        assert casts[remembering._client] < 0.8 * casts[casting._client]
    finally:
        remembering.close()
        casting.close()


def test_clients_are_released_on_every_path(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    def live_clients() -> int:
        return sum(pybullet.isConnected(physicsClientId=c) for c in range(64))

    before = live_clients()
    env = BrainNavEnv(render_mode="rgb_array")  # a private world
    assert live_clients() == before + 1
    env.close()
    env.close()  # idempotent
    assert live_clients() == before
    headless = [BrainNavEnv(), BrainNavEnv(task="vssg")]  # one shared world of the map
    assert live_clients() == before + 1
    assert headless[0]._client == headless[1]._client
    headless[0].close()
    headless[0].close()  # idempotent: the other still holds the world
    assert live_clients() == before + 1
    headless[1].close()
    assert live_clients() == before

    def broken_husky(client: int) -> int:
        raise RuntimeError("mesh missing")

    monkeypatch.setattr(bullet, "add_husky", broken_husky)
    with pytest.raises(RuntimeError, match="mesh missing"):
        BrainNavEnv(render_mode="rgb_array")  # the Husky is built for frames only
    assert live_clients() == before  # the half-built env's client is gone too
    unreachable = tmp_path / "walled.json"
    unreachable.write_text(
        '{"name": "walled", "bounds": {"x_max": 4, "y_max": 3}, '
        '"boxes": [{"center": [2, 1.5], "size": [0.4, 3]}], '
        '"start": {"x": 1, "y": 1.5}, "goal": {"x": 3.2, "y": 1.5}}'
    )
    with pytest.raises(MapError, match="cannot be reached"):
        BrainNavEnv(map_path=unreachable)
    assert live_clients() == before
