"""``bgrl bench sim``: the simulator's costs, each against a peer measured in the same run.

Figures (all single process, single thread):

- **env steps/s** vs raw ``pybullet.rayTestBatch`` of 10 rays on the same geometry from
  the same poses (the ray cast is the floor cost of a step; aim: ratio >= 0.5). The two are
  measured in interleaved rounds and the median round is reported, so load from other
  processes hits both alike.
- **frame render** (third-person TinyRenderer frame at 320 x 240) and the **top-down
  image**, against the frame budget of the default 5 fps stream; plus JPEG/PNG encoding.
- **oracle**: cold build of the default map's lattice (no cache) against loading it from
  the on-disk cache; query time per state (``optimal_actions``, ``cost_to_go``) against one
  env step.
- **service step**: a step through the HTTP app (in-process client, no network) against a
  direct env step and against a no-op request (``GET /health``) through the same client.
"""

from __future__ import annotations

import math
import platform
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pybullet_data

from services.sim import bullet
from services.sim.bullet import pybullet
from services.sim.env import RAY_ANGLES_RAD, RAY_LENGTH_M, BrainNavEnv
from services.sim.imaging import encode_image
from services.sim.maps import DEFAULT_MAP_PATH, FOOTPRINT_RADIUS_M, NavMap, load_map
from services.sim.oracle import Oracle, build_cost_to_go
from services.sim.world import RAY_HEIGHT_M

Progress = Callable[[str], None]
RAYCAST_RATIO_AIM = 0.5
MAX_EPISODE_STEPS = 120


def _summary_ms(seconds: list[float]) -> dict[str, float]:
    ms = sorted(1000.0 * s for s in seconds)
    return {
        "mean": statistics.fmean(ms),
        "p50": ms[len(ms) // 2],
        "p95": ms[min(len(ms) - 1, math.ceil(0.95 * len(ms)) - 1)],
    }


def _raycast_world(nav_map: NavMap) -> int:
    """A DIRECT client with the map's floor, walls and boxes (collision shapes only)."""
    cid = pybullet.connect(pybullet.DIRECT)
    pybullet.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    pybullet.loadURDF("plane.urdf", physicsClientId=cid)
    b, t, wh = nav_map.bounds, nav_map.wall_thickness, nav_map.wall_height
    width, depth = b.x_max - b.x_min, b.y_max - b.y_min
    mid_x, mid_y = (b.x_min + b.x_max) / 2.0, (b.y_min + b.y_max) / 2.0
    boxes = [
        (mid_x, b.y_min - t / 2, width + 2 * t, t, wh, 0.0),
        (mid_x, b.y_max + t / 2, width + 2 * t, t, wh, 0.0),
        (b.x_min - t / 2, mid_y, t, depth, wh, 0.0),
        (b.x_max + t / 2, mid_y, t, depth, wh, 0.0),
        *((*box.center, *box.size, box.height, box.yaw) for box in nav_map.boxes),
    ]
    for cx, cy, sx, sy, h, yaw in boxes:
        shape = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=[sx / 2, sy / 2, h / 2], physicsClientId=cid
        )
        pybullet.createMultiBody(
            0,
            shape,
            basePosition=[cx, cy, h / 2],
            baseOrientation=pybullet.getQuaternionFromEuler([0.0, 0.0, yaw]),
            physicsClientId=cid,
        )
    return cid


def _random_actions(rng: np.random.Generator, n: int) -> list[int]:
    return rng.integers(0, 3, size=n).tolist()


def _run_env(env: BrainNavEnv, actions: list[int], seed: int) -> list[tuple[float, float, float]]:
    """Step ``env`` through ``actions`` (reset at episode end); returns the poses visited."""
    poses = []
    env.reset(seed=seed)
    episode_steps = 0
    for action in actions:
        _, _, terminated, _, info = env.step(action)
        poses.append(info["pose"])
        episode_steps += 1
        if terminated or episode_steps >= MAX_EPISODE_STEPS:
            env.reset()
            episode_steps = 0
    return poses


def bench_env_vs_raycast(
    nav_map: NavMap, *, steps: int, rounds: int, seed: int, progress: Progress
) -> dict[str, Any]:
    """Env steps/s against raw 10-ray ``rayTestBatch`` calls/s, interleaved rounds."""
    rng = np.random.default_rng(seed)
    env = BrainNavEnv(task="sssg", reward_mode="sparse")
    try:
        cid = _raycast_world(nav_map)
    except BaseException:
        env.close()
        raise
    try:
        per_round = max(1, steps // rounds)
        poses = _run_env(env, _random_actions(rng, per_round), seed)  # warm-up + ray poses
        ray_z = min(
            RAY_HEIGHT_M, 0.5 * min([nav_map.wall_height, *(b.height for b in nav_map.boxes)])
        )
        batches = []
        for x, y, yaw in poses:
            origin = [x, y, ray_z]
            ends = [
                [x + RAY_LENGTH_M * math.cos(yaw + a), y + RAY_LENGTH_M * math.sin(yaw + a), ray_z]
                for a in RAY_ANGLES_RAD.tolist()
            ]
            batches.append(([origin] * len(ends), ends))
        env_rates, ray_rates = [], []
        for r in range(rounds):
            actions = _random_actions(rng, per_round)
            start = time.perf_counter()
            _run_env(env, actions, seed + r)
            env_rates.append(per_round / (time.perf_counter() - start))
            start = time.perf_counter()
            for origins, ends in batches:
                pybullet.rayTestBatch(origins, ends, physicsClientId=cid)
            ray_rates.append(len(batches) / (time.perf_counter() - start))
            progress(f"env vs rays {r + 1}/{rounds}")
    finally:
        env.close()
        bullet.disconnect(cid)
    env_rate = statistics.median(env_rates)
    ray_rate = statistics.median(ray_rates)
    ratio = env_rate / ray_rate
    return {
        "steps_measured": per_round * rounds,
        "rounds": rounds,
        "env_steps_per_s": env_rate,
        "raycast_batches_per_s": ray_rate,
        "ratio_env_to_raycast": ratio,
        "aim_ratio": RAYCAST_RATIO_AIM,
        "meets_aim": ratio >= RAYCAST_RATIO_AIM,
        "env_step_us": 1e6 / env_rate,
        "raycast_batch_us": 1e6 / ray_rate,
        "policy": "uniformly random actions, reset on termination or after 120 steps",
    }


def bench_render(*, frames: int, seed: int, stream_fps: float, progress: Progress) -> dict:
    """Third-person frame and top-down image times, plus encoding, against the frame budget."""
    rng = np.random.default_rng(seed)
    env = BrainNavEnv(task="sssg", render_mode="rgb_array", render_width=320, render_height=240)
    camera, top_down, jpeg, png = [], [], [], []
    try:
        env.reset(seed=seed)
        env.render()  # first call builds TinyRenderer state
        shape = None
        for i in range(frames):
            _, _, terminated, _, _ = env.step(int(rng.integers(0, 3)))
            if terminated:
                env.reset()
            start = time.perf_counter()
            frame = env.render()
            camera.append(time.perf_counter() - start)
            shape = frame.shape
            start = time.perf_counter()
            image = env.top_down_image()
            top_down.append(time.perf_counter() - start)
            start = time.perf_counter()
            encode_image(frame, "jpeg")
            jpeg.append(time.perf_counter() - start)
            start = time.perf_counter()
            encode_image(frame, "png")
            png.append(time.perf_counter() - start)
            if (i + 1) % 10 == 0:
                progress(f"render {i + 1}/{frames}")
    finally:
        env.close()
    budget_ms = 1000.0 / stream_fps
    camera_ms = _summary_ms(camera)
    return {
        "frames": frames,
        "camera_frame_shape": list(shape) if shape else None,
        "top_down_shape": list(image.shape),
        "camera_frame_ms": camera_ms,
        "top_down_ms": _summary_ms(top_down),
        "jpeg_encode_ms": _summary_ms(jpeg),
        "png_encode_ms": _summary_ms(png),
        "stream_fps": stream_fps,
        "frame_budget_ms": budget_ms,
        "camera_frame_fraction_of_budget": camera_ms["mean"] / budget_ms,
    }


def bench_oracle(
    nav_map: NavMap, *, queries: int, env_step_us: float, seed: int, progress: Progress
) -> dict[str, Any]:
    """Cold lattice build vs cache load; per-state query time vs one env step."""
    start = time.perf_counter()
    cost = build_cost_to_go(nav_map)
    build_s = time.perf_counter() - start
    progress("oracle built")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "cost.npz"
        np.savez_compressed(path, cost=cost)
        start = time.perf_counter()
        with np.load(path) as data:
            loaded = data["cost"]
        load_s = time.perf_counter() - start
    oracle = Oracle(nav_map, loaded)
    rng = np.random.default_rng(seed)
    b = nav_map.bounds
    poses: list[tuple[float, float, float]] = []
    while len(poses) < queries:
        x = float(rng.uniform(b.x_min, b.x_max))
        y = float(rng.uniform(b.y_min, b.y_max))
        if nav_map.clearance(x, y) >= FOOTPRINT_RADIUS_M:
            poses.append((x, y, float(rng.uniform(-math.pi, math.pi))))
    start = time.perf_counter()
    for pose in poses:
        oracle.optimal_actions(*pose)
    optimal_us = 1e6 * (time.perf_counter() - start) / queries
    start = time.perf_counter()
    for pose in poses:
        oracle.cost_to_go(*pose)
    cost_us = 1e6 * (time.perf_counter() - start) / queries
    progress("oracle queried")
    return {
        "lattice_shape": list(cost.shape),
        "lattice_mb": cost.nbytes / 2**20,
        "build_cold_s": build_s,
        "cache_load_s": load_s,
        "ratio_build_to_cache_load": build_s / load_s,
        "queries": queries,
        "optimal_actions_us": optimal_us,
        "cost_to_go_us": cost_us,
        "ratio_optimal_actions_to_env_step": optimal_us / env_step_us,
        "ratio_cost_to_go_to_env_step": cost_us / env_step_us,
        "note": "cost_to_go rolls the oracle policy out to the goal, so it grows with distance",
    }


def bench_service_step(*, steps: int, seed: int, progress: Progress) -> dict[str, Any]:
    """A step through the HTTP app (in-process, no network) against a direct env step."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # starlette asks for httpx2, httpx works
        from fastapi.testclient import TestClient

    from services.sim.app import create_app
    from services.sim.settings import SimSettings

    rng = np.random.default_rng(seed)
    actions = _random_actions(rng, steps)
    env = BrainNavEnv(task="sssg")
    try:
        start = time.perf_counter()
        _run_env(env, actions, seed)
        direct_s = (time.perf_counter() - start) / steps
    finally:
        env.close()
    app = create_app(SimSettings(lsl_markers=False, log_level="WARNING"))  # no per-request log
    with TestClient(app) as client:
        session_id = client.post("/sessions", json={"seed": seed}).json()["id"]
        start = time.perf_counter()
        for action in actions:
            body = client.post(f"/sessions/{session_id}/step", json={"action": action}).json()
            if body["terminated"] or body["truncated"]:
                client.post(f"/sessions/{session_id}/reset", json={})
        http_s = (time.perf_counter() - start) / steps
        start = time.perf_counter()
        for _ in range(steps):
            client.get("/health")
        noop_s = (time.perf_counter() - start) / steps
    progress("service steps")
    return {
        "steps": steps,
        "http_step_ms": 1000.0 * http_s,
        "http_health_ms": 1000.0 * noop_s,
        "direct_env_step_ms": 1000.0 * direct_s,
        "ratio_http_to_direct": http_s / direct_s,
        "ratio_http_step_to_health": http_s / noop_s,
        "note": "in-process ASGI test client (its per-request cost is the health round trip); "
        "a step includes the oracle verdict, JSON encoding and resets at episode ends",
    }


def run(
    *,
    env_steps: int = 20_000,
    rounds: int = 10,
    frames: int = 60,
    oracle_queries: int = 2_000,
    service_steps: int = 300,
    stream_fps: float = 5.0,
    seed: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Run every sim benchmark and return the figures as a JSON-ready dict."""
    report: Progress = progress if progress is not None else (lambda _message: None)
    nav_map = load_map(DEFAULT_MAP_PATH)
    started = time.perf_counter()
    env = bench_env_vs_raycast(nav_map, steps=env_steps, rounds=rounds, seed=seed, progress=report)
    render = bench_render(frames=frames, seed=seed, stream_fps=stream_fps, progress=report)
    oracle = bench_oracle(
        nav_map,
        queries=oracle_queries,
        env_step_us=env["env_step_us"],
        seed=seed,
        progress=report,
    )
    service = bench_service_step(steps=service_steps, seed=seed, progress=report)
    return {
        "benchmark": "sim",
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "processor": platform.processor() or platform.machine(),
            "pybullet_api": pybullet.getAPIVersion(),
        },
        "parameters": {
            "env_steps": env_steps,
            "rounds": rounds,
            "frames": frames,
            "oracle_queries": oracle_queries,
            "service_steps": service_steps,
            "stream_fps": stream_fps,
            "seed": seed,
            "map": DEFAULT_MAP_PATH.name,
        },
        "env_step": env,
        "render": render,
        "oracle": oracle,
        "service": service,
        "wall_time_s": time.perf_counter() - started,
    }
