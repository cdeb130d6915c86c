"""Oracle: lattice BFS, exact path lengths, the oracle policy, disk cache, noisy feedback."""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import services.sim.oracle as oracle_module
from services.core.actions import Action
from services.sim.env import BrainNavEnv
from services.sim.maps import DEFAULT_MAP_PATH, NavMap, load_map, parse_map
from services.sim.oracle import NoisyOracleFeedback, Oracle


def corridor_map(goal_x: float = 3.05) -> NavMap:
    """A 4 x 2 m room; start (1, 1), goal (goal_x, 1): forward moves reach x = 2.8 after 6."""
    return parse_map(
        {
            "name": "corridor",
            "bounds": {"x_max": 4.0, "y_max": 2.0},
            "start": {"x": 1.0, "y": 1.0, "yaw": 0.0},
            "start_jitter": 0.0,
            "goal": {"x": goal_x, "y": 1.0},
        }
    )


def test_hand_built_map_known_answers() -> None:
    oracle = Oracle.for_map(corridor_map())
    # Six forward moves: x = 2.5 is 0.55 m from the goal, x = 2.8 is 0.25 m.
    assert oracle.cost_to_go(1.0, 1.0, 0.0) == 6
    assert oracle.rollout(1.0, 1.0, 0.0) == [Action.FORWARD] * 6
    assert oracle.optimal_actions(1.0, 1.0, 0.0) == {Action.FORWARD}
    # Facing away: six turns either way, then six moves; the tie favours left.
    assert oracle.cost_to_go(1.0, 1.0, math.pi) == 12
    assert oracle.optimal_actions(1.0, 1.0, math.pi) == {Action.TURN_LEFT, Action.TURN_RIGHT}
    assert oracle.policy_action(1.0, 1.0, math.pi) == Action.TURN_LEFT
    # Facing +y: three right turns, then six moves.
    assert oracle.cost_to_go(1.0, 1.0, math.pi / 2) == 9
    assert oracle.optimal_actions(1.0, 1.0, math.pi / 2) == {Action.TURN_RIGHT}
    # In the goal: zero; inside a wall: unreachable.
    assert oracle.cost_to_go(2.9, 1.0, 0.0) == 0
    assert oracle.cost_to_go(0.1, 1.0, 0.0) == math.inf
    assert oracle.optimal_actions(0.1, 1.0, 0.0) == frozenset()


def test_default_map_path_length_and_straight_line_blocked() -> None:
    nav_map = load_map(DEFAULT_MAP_PATH)
    oracle = Oracle.for_map(nav_map)
    s = nav_map.start
    length = oracle.cost_to_go(s.x, s.y, s.yaw)
    assert 17 <= length <= 19
    # Heading straight for the goal collides before the goal radius is reached.
    distance = math.hypot(nav_map.goal.x - s.x, nav_map.goal.y - s.y)
    f = 1.0 - nav_map.goal.radius / distance
    end_x, end_y = s.x + f * (nav_map.goal.x - s.x), s.y + f * (nav_map.goal.y - s.y)
    assert nav_map.geometry.move_collides(s.x, s.y, end_x, end_y)


def _drive_with_oracle(env: BrainNavEnv, seed: int) -> tuple[int, int, bool]:
    _, info = env.reset(seed=seed)
    steps = 0
    terminated = truncated = False
    while not (terminated or truncated) and steps < 200:
        _, _, terminated, truncated, step_info = env.step(env.oracle.policy_action(*env.pose))
        steps += 1
    return info["shortest_path_steps"], steps, bool(step_info["is_success"])


def test_oracle_policy_takes_exactly_shortest_path_steps() -> None:
    sssg = BrainNavEnv(task="sssg")
    vssg = BrainNavEnv(task="vssg")
    try:
        l_sssg, taken, success = _drive_with_oracle(sssg, 0)
        assert success and taken == l_sssg
        lengths = []
        for seed in range(40):
            shortest, taken, success = _drive_with_oracle(vssg, seed)
            assert success and taken == shortest, f"seed {seed}: {taken} != {shortest}"
            lengths.append(shortest)
        assert min(lengths) >= 17 and max(lengths) <= 19
    finally:
        sssg.close()
        vssg.close()


def test_policy_action_is_optimal_and_decreases_cost_by_one() -> None:
    nav_map = load_map(DEFAULT_MAP_PATH)
    oracle = Oracle.for_map(nav_map)
    rng = np.random.default_rng(0)
    checked = 0
    while checked < 30:
        x, y = rng.uniform(0.5, 10.5), rng.uniform(0.5, 11.5)
        yaw = rng.integers(12) * math.pi / 6
        if nav_map.geometry.collides(x, y) or not math.isfinite(oracle.cost_to_go(x, y, yaw)):
            continue
        action = oracle.policy_action(x, y, yaw)
        assert action in oracle.optimal_actions(x, y, yaw)
        if action == Action.FORWARD:
            nx, ny, nyaw = x + 0.3 * math.cos(yaw), y + 0.3 * math.sin(yaw), yaw
        else:
            nx, ny, nyaw = x, y, yaw + (math.pi / 6 if action == Action.TURN_LEFT else -math.pi / 6)
        assert oracle.cost_to_go(nx, ny, nyaw) == oracle.cost_to_go(x, y, yaw) - 1
        checked += 1


def test_default_map_detour_never_leads_away_from_goal() -> None:
    env = BrainNavEnv(task="vssg")
    try:
        for seed in range(5):
            obs, _ = env.reset(seed=seed)
            distances = [float(obs[10])]
            terminated = False
            while not terminated:
                obs, _, terminated, _, _ = env.step(env.oracle.policy_action(*env.pose))
                distances.append(float(obs[10]))
            assert all(b <= a + 1e-6 for a, b in itertools.pairwise(distances))
    finally:
        env.close()


def test_disk_cache_round_trip(tmp_path: Path) -> None:
    nav_map = corridor_map(goal_x=3.1)
    built = Oracle.for_map(nav_map, tmp_path / "oracle")
    files = list((tmp_path / "oracle").iterdir())
    assert [f.name for f in files] == [f"{Oracle.cache_key(nav_map)}.npz"]  # no temp file left
    Oracle.clear_memory()
    loaded = Oracle.for_map(nav_map, tmp_path / "oracle")
    assert loaded is not built
    np.testing.assert_array_equal(loaded.cost, built.cost)
    # A different map gets a different key.
    assert Oracle.cache_key(corridor_map(goal_x=3.2)) != Oracle.cache_key(nav_map)


def test_corrupt_cache_file_is_rebuilt(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    nav_map = corridor_map(goal_x=3.15)
    path = tmp_path / f"{Oracle.cache_key(nav_map)}.npz"
    path.write_bytes(b"not an npz")
    oracle = Oracle.for_map(nav_map, tmp_path)
    assert oracle.cost_to_go(1.0, 1.0, 0.0) == 6
    assert "unreadable oracle cache" in caplog.text
    with np.load(path) as data:  # replaced by the rebuilt lattice
        np.testing.assert_array_equal(data["cost"], oracle.cost)


def corridor_file(folder: Path, goal_x: float) -> Path:
    """:func:`corridor_map` as a map file (its lattice builds in milliseconds)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"corridor_{goal_x}.json"
    path.write_text(json.dumps(corridor_map(goal_x).model_dump(mode="json")))
    return path


def test_without_a_cache_dir_nothing_is_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    map_path = corridor_file(tmp_path / "maps", goal_x=3.35)
    workdir = tmp_path / "work"
    workdir.mkdir()
    monkeypatch.chdir(workdir)
    monkeypatch.setenv("BGRL_DATA_DIR", str(tmp_path / "data"))  # ignored: no env reads
    Oracle._memory.pop(Oracle.cache_key(load_map(map_path)), None)  # a cold build
    env = gym.make("services.sim:BrainNav-SSSG-v0", map_path=map_path)
    try:
        env.reset(seed=0)
        env.step(0)
    finally:
        env.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["maps", "work"]
    assert list(workdir.iterdir()) == []


def test_gym_make_uses_the_cache_dir_it_is_given(tmp_path: Path) -> None:
    map_path = corridor_file(tmp_path / "maps", goal_x=3.4)
    key = Oracle.cache_key(load_map(map_path))
    Oracle._memory.pop(key, None)
    env = gym.make(
        "services.sim:BrainNav-VSSG-v0", map_path=map_path, oracle_cache_dir=tmp_path / "cache"
    )
    env.close()
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [f"{key}.npz"]


def test_concurrent_cold_starts_share_one_build(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    builds: list[str] = []
    real_build = oracle_module.build_cost_to_go

    def counting_build(nav_map: NavMap) -> np.ndarray:
        builds.append(nav_map.name)
        time.sleep(0.2)  # keep the build open while the other threads arrive
        return real_build(nav_map)

    monkeypatch.setattr(oracle_module, "build_cost_to_go", counting_build)
    maps = [corridor_map(goal_x=3.05), corridor_map(goal_x=3.25)]
    for m in maps:
        Oracle._memory.pop(Oracle.cache_key(m), None)
    barrier = threading.Barrier(8)

    def cold_start(i: int) -> Oracle:
        barrier.wait()
        return Oracle.for_map(maps[i % 2], tmp_path if i % 4 == 0 else None)

    with ThreadPoolExecutor(8) as pool:
        oracles = list(pool.map(cold_start, range(8)))
    assert sorted(builds) == ["corridor", "corridor"]  # one build per map
    assert {id(o) for o in oracles[0::2]} == {id(oracles[0])}
    assert {id(o) for o in oracles[1::2]} == {id(oracles[1])}
    assert oracles[0] is not oracles[1]


def test_lattice_invariants_are_checked(monkeypatch: pytest.MonkeyPatch) -> None:
    assert oracle_module.lattice_margins() == (40, 31)  # 0.4 m radius, 0.3 m moves, 1 cm cells
    oracle_module.check_lattice_invariants()
    monkeypatch.setattr(oracle_module, "FOOTPRINT_RADIUS_M", 0.3)  # margin 30 < span 31
    with pytest.raises(RuntimeError, match="flat indexing would wrap"):
        oracle_module.check_lattice_invariants()
    with pytest.raises(RuntimeError, match="flat indexing would wrap"):
        oracle_module.build_cost_to_go(corridor_map())  # free cells now reach the border
    monkeypatch.setattr(oracle_module, "FOOTPRINT_RADIUS_M", 0.4)
    monkeypatch.setattr(oracle_module, "CELL_M", 0.0075)  # margin 53, span 41: still fine
    oracle_module.check_lattice_invariants()


@pytest.mark.parametrize(
    ("x", "y", "yaw"),
    [(1e308, 1.0, 0.0), (-1e308, 1.0, 0.0), (1.0, 1e308, 0.0), (math.nan, 1.0, 0.0)],
)
def test_queries_far_off_the_map_are_unreachable_not_errors(x: float, y: float, yaw: float) -> None:
    oracle = Oracle.for_map(corridor_map())
    assert oracle.cost_to_go(x, y, yaw) == math.inf
    assert oracle.optimal_actions(x, y, yaw) == frozenset()
    assert oracle.policy_action(x, y, yaw) is None


def test_noisy_feedback_accuracy_and_seeding() -> None:
    perfect = NoisyOracleFeedback(1.0, seed=0)
    assert all(perfect.feedback(True) for _ in range(50))
    assert not any(perfect.feedback(False) for _ in range(50))
    inverted = NoisyOracleFeedback(0.0, seed=0)
    assert not any(inverted.feedback(True) for _ in range(50))

    noisy = NoisyOracleFeedback(0.6, seed=1)
    hits = sum(noisy.feedback(True) for _ in range(20_000))
    assert abs(hits / 20_000 - 0.6) < 0.015

    split = NoisyOracleFeedback(good_accuracy=0.9, bad_accuracy=0.55, seed=2)
    good = sum(split.feedback(True) for _ in range(20_000)) / 20_000
    bad = sum(not split.feedback(False) for _ in range(20_000)) / 20_000
    assert abs(good - 0.9) < 0.015 and abs(bad - 0.55) < 0.015

    a, b = NoisyOracleFeedback(0.7, seed=5), NoisyOracleFeedback(0.7, seed=5)
    assert [a.feedback(i % 2 == 0) for i in range(100)] == [
        b.feedback(i % 2 == 0) for i in range(100)
    ]


def test_noisy_feedback_rejects_bad_accuracy() -> None:
    with pytest.raises(ValueError, match="accuracy"):
        NoisyOracleFeedback()
    with pytest.raises(ValueError, match="within"):
        NoisyOracleFeedback(1.2)
    with pytest.raises(ValueError, match="bad_accuracy"):
        NoisyOracleFeedback(0.7, bad_accuracy=-0.1)


def _uncached_cost(oracle: Oracle, x: float, y: float, yaw: float) -> float:
    """The path length by walking the whole path (rollout remembers nothing)."""
    actions = oracle.rollout(x, y, yaw)
    return math.inf if actions is None else float(len(actions))


def _sweep_like_poses(seed: int, n_steps: int) -> list[tuple[float, float, float]]:
    """Poses of a VSSG env driven by random actions (the queries of the dense reward)."""
    env = BrainNavEnv(task="vssg")
    rng = np.random.default_rng(seed)
    poses = []
    try:
        env.reset(seed=seed)
        for _ in range(n_steps):
            poses.append(env.pose)
            _, _, terminated, _, _ = env.step(int(rng.integers(3)))
            if terminated:
                env.reset()
    finally:
        env.close()
    return poses


def test_remembered_path_lengths_equal_walked_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    nav_map = load_map(DEFAULT_MAP_PATH)
    oracle = Oracle(nav_map, Oracle.for_map(nav_map).cost)  # a fresh, empty memo
    rng = np.random.default_rng(3)
    random_poses = [
        (float(rng.uniform(0.5, 10.5)), float(rng.uniform(0.5, 11.5)), float(rng.uniform(-4, 4)))
        for _ in range(100)
    ]
    poses = _sweep_like_poses(0, 400) + random_poses
    first = [oracle.cost_to_go(*pose) for pose in poses]
    assert len(oracle._path_memo) > 0
    second = [oracle.cost_to_go(*pose) for pose in reversed(poses)][::-1]  # from the memo
    walked = [_uncached_cost(oracle, *pose) for pose in poses]
    assert first == walked and second == walked
    assert any(math.isinf(c) for c in walked) and any(0 < c < math.inf for c in walked)
    # A memo that keeps emptying itself gives the same answers.
    monkeypatch.setattr(oracle_module, "PATH_MEMO_MAX_STATES", 30)
    small = Oracle(nav_map, oracle.cost)
    assert [small.cost_to_go(*pose) for pose in poses] == walked
    assert len(small._path_memo) <= 30


def test_remembered_suffix_still_obeys_the_rollout_limit(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(oracle_module, "MAX_ROLLOUT_STEPS", 10)
    nav_map = corridor_map()
    oracle = Oracle(nav_map, Oracle.for_map(nav_map).cost)
    assert oracle.cost_to_go(1.0, 1.0, 0.0) == 6  # remembers the six states of its path
    # Facing away: six turns reach the remembered start state, 6 + 6 > 10 actions.
    assert oracle.rollout(1.0, 1.0, math.pi) is None
    assert oracle.cost_to_go(1.0, 1.0, math.pi) == math.inf
    monkeypatch.setattr(oracle_module, "MAX_ROLLOUT_STEPS", 12)
    assert oracle.cost_to_go(1.0, 1.0, math.pi) == 12 == len(oracle.rollout(1.0, 1.0, math.pi))
