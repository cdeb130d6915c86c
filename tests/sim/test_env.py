"""BrainNavEnv: spaces, observations, rewards, termination, seeding, check_env, rendering."""

from __future__ import annotations

import math
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import services.sim  # noqa: F401  (registers the ids)
from services.core.actions import Action
from services.sim.env import BrainNavEnv
from services.sim.maps import FOOTPRINT_RADIUS_M, MAPS_DIR


@pytest.fixture(scope="module")
def env():
    environment = BrainNavEnv(task="sssg", reward_mode="sparse", render_mode="rgb_array")
    yield environment
    environment.close()


def test_spaces_and_reset_observation(env: BrainNavEnv) -> None:
    obs, info = env.reset(seed=0)
    assert env.action_space == gym.spaces.Discrete(3)
    assert obs.shape == (13,) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    # Start (2, 6) facing +x: the +-90 deg rays hit the nearest box face or floor wall
    # straight below / above (the default map's boxes are axis-aligned).
    boxes = [b for b in env.nav_map.boxes if abs(b.center[0] - 2.0) <= b.size[0] / 2]
    above = min([b.center[1] - b.size[1] / 2 for b in boxes if b.center[1] > 6.0] + [12.0])
    below = max([b.center[1] + b.size[1] / 2 for b in boxes if b.center[1] < 6.0] + [0.0])
    assert obs[9] == pytest.approx(above - 6.0, abs=1e-3)
    assert obs[0] == pytest.approx(6.0 - below, abs=1e-3)
    assert all(b.yaw == 0.0 for b in env.nav_map.boxes)
    assert obs[10] == pytest.approx(4.6, abs=1e-4)  # goal (6.6, 6) is 4.6 m ahead
    assert obs[11] == pytest.approx(0.0, abs=1e-6) and obs[12] == pytest.approx(0.0, abs=1e-6)
    assert info["pose"] == (2.0, 6.0, 0.0)
    assert 17 <= info["shortest_path_steps"] <= 19
    assert info["is_success"] is False and info["collision"] is False


@pytest.mark.parametrize("reward_mode", ["rich", "shaped", "dense"])
def test_check_env_passes(reward_mode: str) -> None:
    environment = gym.make(
        "services.sim:BrainNav-VSSG-v0", reward_mode=reward_mode, render_mode="rgb_array"
    )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # any checker warning fails the test
            check_env(environment.unwrapped)
    finally:
        environment.close()


def test_make_registered_ids_and_time_limit() -> None:
    for env_id in ("services.sim:BrainNav-SSSG-v0", "services.sim:BrainNav-VSSG-v0"):
        environment = gym.make(env_id, reward_mode="rich")
        try:
            environment.reset(seed=1)
            truncated = terminated = False
            steps = 0
            while not (terminated or truncated):
                _, _, terminated, truncated, info = environment.step(Action.TURN_LEFT)
                steps += 1
                assert info["is_success"] is False
            assert truncated and not terminated and steps == 120
        finally:
            environment.close()


def test_turn_rewards_sparse_and_rich() -> None:
    for mode in ("sparse", "rich"):
        environment = BrainNavEnv(reward_mode=mode)
        try:
            environment.reset(seed=0)
            obs, reward, terminated, _, info = environment.step(Action.TURN_LEFT)
            assert obs[12] == pytest.approx(math.radians(30), abs=1e-6)
            heading_error = abs(obs[11] - obs[12])
            expected = -1.0 if mode == "sparse" else -1.0 - obs[10] - 0.3 * heading_error
            assert reward == pytest.approx(expected, abs=1e-5)
            assert not terminated and info["collision"] is False
        finally:
            environment.close()


def _oracle_path(environment: BrainNavEnv) -> list[int]:
    return environment.oracle.rollout(*environment.pose)


@pytest.mark.parametrize("gamma", [0.99, 0.9])
@pytest.mark.parametrize(
    ("name", "seed", "plan"),
    [
        ("to the goal", 3, _oracle_path),
        ("into the wall", 4, lambda e: [Action.FORWARD] * 20),
        ("turn, then drive", 5, lambda e: [Action.TURN_LEFT] * 3 + [Action.FORWARD] * 40),
        ("random, cut off", 6, lambda e: list(np.random.default_rng(6).integers(0, 3, 25))),
    ],
)
def test_shaped_reward_is_potential_based(name: str, seed: int, plan, gamma: float) -> None:
    """Over a trajectory, sum_t gamma^t F_t = gamma^T Phi(s_T) - Phi(s_0) (Ng et al. 1999),
    with F the shaped minus the sparse reward, Phi = -(oracle's path) and Phi = 0 at the
    end of a terminated episode."""
    sparse = BrainNavEnv(task="vssg", reward_mode="sparse")
    shaped = BrainNavEnv(task="vssg", reward_mode="shaped", shaping_gamma=gamma)
    try:
        _, info = sparse.reset(seed=seed)
        _, shaped_info = shaped.reset(seed=seed)
        phi_0 = -float(info["shortest_path_steps"])
        assert phi_0 == shaped.potential() and info == shaped_info
        discounted, t, terminated = 0.0, 0, False
        for action in plan(sparse):
            _, r_sparse, terminated, _, step_info = sparse.step(int(action))
            _, r_shaped, shaped_terminated, _, _ = shaped.step(int(action))
            assert shaped_terminated == terminated
            discounted += gamma**t * (r_shaped - r_sparse)
            t += 1
            if terminated:
                break
        phi_t = 0.0 if terminated else shaped.potential()
        assert discounted == pytest.approx(gamma**t * phi_t - phi_0, abs=1e-9)
        outcome = "goal" if step_info["is_success"] else "collision" if terminated else "cut"
        assert outcome == {"to the goal": "goal", "into the wall": "collision"}.get(name, outcome)
    finally:
        sparse.close()
        shaped.close()


def test_shaped_reward_prefers_the_oracle_action() -> None:
    """From the start, an optimal action earns more than a step away from the path."""
    environment = BrainNavEnv(reward_mode="shaped")
    try:
        environment.reset(seed=0)
        best = environment.oracle.policy_action(*environment.pose)
        _, good, *_ = environment.step(best)
        environment.reset(seed=0)
        worse = next(a for a in range(3) if a not in environment.optimal_actions())
        _, bad, *_ = environment.step(worse)
        assert good > -1.0 > bad  # the sparse step reward is -1 either way
    finally:
        environment.close()


def _discounted_return(environment: BrainNavEnv, actions, gamma: float) -> tuple[float, dict]:
    total, info = 0.0, {}
    for t, action in enumerate(actions):
        _, reward, terminated, truncated, info = environment.step(int(action))
        total += gamma**t * reward
        if terminated or truncated:
            break
    return total, info


def _drive_into_the_wall(environment: BrainNavEnv) -> tuple[float, float, dict[str, Any]]:
    """From SSSG's start (seed 0), forward until the episode ends (facing +x from (2, 6):
    the wall at x = 4 stops the robot): the oracle's path from the last pose, the last
    reward and its info."""
    environment.reset(seed=0)
    for _ in range(20):
        before = environment.path_cost()
        _, reward, terminated, _, info = environment.step(Action.FORWARD)
        if terminated:
            break
    return before, float(reward), info


def test_dense_reward_values_on_a_hand_built_case() -> None:
    """By hand from the SSSG start: each step costs 1 + alpha * c(s'), the goal pays +100,
    a crash costs 100 + alpha * c(s) / (1 - gamma), c the oracle's path in actions."""
    gamma, alpha = 0.9, 0.25
    environment = BrainNavEnv(
        task="sssg", reward_mode="dense", shaping_gamma=gamma, distance_coef=alpha
    )
    try:
        _, info = environment.reset(seed=0)
        c = info["shortest_path_steps"]
        rewards, terminated = [], False
        while not terminated:
            action = environment.oracle.policy_action(*environment.pose)
            _, reward, terminated, _, step_info = environment.step(action)
            rewards.append(reward)
        assert step_info["is_success"] is True and len(rewards) == c
        expected = [-1.0 - alpha * (c - 1 - t) for t in range(c - 1)] + [100.0]
        assert rewards == pytest.approx(expected)
        before, reward, step_info = _drive_into_the_wall(environment)
        assert step_info["collision"] is True
        assert reward == pytest.approx(-100.0 - alpha * before / (1.0 - gamma))
    finally:
        environment.close()


def test_dense_reward_defaults_alpha_0_3_and_a_crash_costs_the_step_cost_for_ever() -> None:
    """The default dense reward (alpha 0.3, gamma 0.99): a turn from the SSSG start costs
    1 + 0.3 c(s'); a crash at s costs 100 + 0.3 c(s) / 0.01, exactly the step cost at s
    summed for ever."""
    environment = BrainNavEnv(task="sssg", reward_mode="dense")
    try:
        assert environment.distance_coef == 0.3 and environment.shaping_gamma == 0.99
        environment.reset(seed=0)
        _, reward, terminated, _, _ = environment.step(Action.TURN_LEFT)
        assert not terminated
        assert reward == pytest.approx(-1.0 - 0.3 * environment.path_cost())
        c, reward, info = _drive_into_the_wall(environment)
        assert info["collision"] is True and c > 0
        assert reward == pytest.approx(-100.0 - 30.0 * c)
        assert reward == pytest.approx((-1.0 - 0.3 * c) / (1.0 - 0.99))
    finally:
        environment.close()


@pytest.mark.parametrize("prefix", [0, 2, 4])
def test_dense_crash_never_pays_more_than_the_goal_from_the_same_state(prefix: int) -> None:
    """From states on the way into a wall, crashing (now, or after a detour) returns less
    than following the oracle to the goal, and no more than turning on the spot until the
    time limit (the crash costs what staying there for ever would)."""
    gamma = 0.99
    environment = gym.make("services.sim:BrainNav-VSSG-v0", reward_mode="dense")
    dense = environment.unwrapped
    try:

        def at_state() -> None:
            environment.reset(seed=4)
            for _ in range(prefix):
                assert not environment.step(Action.FORWARD)[2]

        at_state()
        crash, crash_info = _discounted_return(environment, [Action.FORWARD] * 40, gamma)
        assert crash_info["collision"] is True
        at_state()
        goal, goal_info = _discounted_return(environment, _oracle_path(dense), gamma)
        assert goal_info["is_success"] is True
        assert goal > crash
        at_state()
        detour, detour_info = _discounted_return(
            environment, [Action.TURN_RIGHT] * 6 + [Action.FORWARD] * 40, gamma
        )
        assert detour_info["collision"] is True and goal > detour
        at_state()
        spinning, spin_info = _discounted_return(environment, [Action.TURN_LEFT] * 200, gamma)
        assert spin_info["collision"] is False
        assert crash < spinning  # spinning is cut off at 120 steps, the crash is not
    finally:
        environment.close()


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dense_reward_is_best_along_the_oracle_path(seed: int) -> None:
    """c falls by at most 1 an action, so no trajectory costs less than the oracle's path:
    random and half-oracle trajectories return less from the same VSSG start."""
    gamma = 0.99
    environment = gym.make("services.sim:BrainNav-VSSG-v0", reward_mode="dense")
    rng = np.random.default_rng(seed)
    try:
        environment.reset(seed=seed)
        oracle_path = _oracle_path(environment.unwrapped)
        best, info = _discounted_return(environment, oracle_path, gamma)
        assert info["is_success"] is True
        for _ in range(5):
            environment.reset(seed=seed)
            actions, total, t, done = [], 0.0, 0, False
            while not done:
                pose = environment.unwrapped.pose
                oracle = environment.unwrapped.oracle.policy_action(*pose)
                action = oracle if rng.random() < 0.5 else int(rng.integers(0, 3))
                _, reward, terminated, truncated, _ = environment.step(action)
                total += gamma**t * reward
                t, done = t + 1, terminated or truncated
                actions.append(action)
            assert actions != oracle_path  # a random choice differed
            assert total < best
    finally:
        environment.close()


def test_collision_terminates_and_keeps_pose(env: BrainNavEnv) -> None:
    env.reset(seed=0)
    # Facing +x from (2, 6): the wall at x = 4.0 stops the 0.4 m footprint disc.
    for _ in range(20):
        before = env.pose
        _, reward, terminated, _, info = env.step(Action.FORWARD)
        if terminated:
            break
    assert terminated and info["collision"] is True and info["is_success"] is False
    assert reward == -100.0
    assert env.pose == before
    assert before[0] + 0.3 + FOOTPRINT_RADIUS_M > 4.0 > before[0] + FOOTPRINT_RADIUS_M


def test_oracle_path_reaches_goal_with_goal_reward(env: BrainNavEnv) -> None:
    _, info = env.reset(seed=0)
    rewards = []
    terminated = False
    while not terminated:
        action = env.oracle.policy_action(*env.pose)
        assert action in env.optimal_actions()
        _, reward, terminated, _, step_info = env.step(action)
        rewards.append(reward)
    assert step_info["is_success"] is True and step_info["collision"] is False
    assert len(rewards) == info["shortest_path_steps"]
    assert rewards[-1] == 100.0 and all(r == -1.0 for r in rewards[:-1])


def test_observation_cell_is_the_pose_cell_the_observation_describes() -> None:
    environment = BrainNavEnv(task="vssg")
    try:
        obs, _ = environment.reset(seed=3)
        environment.action_space.seed(3)
        goal_x, goal_y = environment.nav_map.goal.x, environment.nav_map.goal.y
        cells = [BrainNavEnv.observation_cell(obs, 0.5)]
        for _ in range(60):
            action = int(environment.action_space.sample())
            obs, _, terminated, _, info = environment.step(action)
            if terminated:
                break
            cell = BrainNavEnv.observation_cell(obs, 0.5)
            x, y, _ = info["pose"]
            for index, offset in ((0, x - goal_x), (1, y - goal_y)):
                if abs(offset / 0.5 - round(offset / 0.5)) > 1e-4:  # float32 at a cell edge
                    assert cell[index] == math.floor(offset / 0.5)
            heading_change = {0: 0, 1: 1, 2: -1}[action]
            assert cell[2] == (cells[-1][2] + heading_change) % 12  # every turn is one step
            cells.append(cell)
        assert len(set(cells)) > 10
    finally:
        environment.close()


def test_same_seed_same_trajectory() -> None:
    def run(seed: int) -> list[tuple[float, float, float]]:
        environment = BrainNavEnv(task="vssg")
        try:
            environment.reset(seed=seed)
            environment.action_space.seed(seed)
            poses = [environment.pose]
            for _ in range(40):
                _, _, terminated, _, _ = environment.step(environment.action_space.sample())
                poses.append(environment.pose)
                if terminated:
                    break
            return poses
        finally:
            environment.close()

    assert run(7) == run(7)
    assert run(7)[0] != run(8)[0]
    start = run(9)[0]
    assert abs(start[0] - 2.0) <= 0.1 and abs(start[1] - 6.0) <= 0.1


def test_invalid_arguments_are_rejected(env: BrainNavEnv) -> None:
    env.reset(seed=0)
    for bad_action in (3, -1, 1.5, np.array([0, 1]), None, "forward"):
        with pytest.raises(ValueError, match="action must be"):
            env.step(bad_action)
    env.step(np.int64(1))  # numpy scalars (what agents sample) are actions
    with pytest.raises(ValueError, match="task"):
        BrainNavEnv(task="maze")
    with pytest.raises(ValueError, match="reward_mode"):
        BrainNavEnv(reward_mode="geodesic")
    with pytest.raises(ValueError, match="distance_coef"):
        BrainNavEnv(reward_mode="dense", distance_coef=0.0)
    with pytest.raises(ValueError, match="shaping_gamma < 1"):
        BrainNavEnv(reward_mode="dense", shaping_gamma=1.0)
    with pytest.raises(ValueError, match="shaping_gamma"):
        BrainNavEnv(reward_mode="shaped", shaping_gamma=0.0)
    with pytest.raises(ValueError, match="render_mode"):
        BrainNavEnv(render_mode="human")


def test_other_map_file() -> None:
    environment = BrainNavEnv(map_path=MAPS_DIR / "open.json")
    try:
        _, info = environment.reset(seed=0)
        assert info["shortest_path_steps"] > 0
        assert environment.nav_map.name == "open"
    finally:
        environment.close()


def test_rendering(env: BrainNavEnv) -> None:
    env.reset(seed=0)
    env.step(Action.TURN_LEFT)
    env.step(Action.FORWARD)
    frame = env.render()
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
    assert frame.std() > 5.0  # a real scene, not a blank image
    image = env.top_down_image()
    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    # The robot disc is drawn at its pose (40 px/m, 0.2 m wall margin, y up).
    x, y, _ = env.pose
    px, py = round((x + 0.2) * 40), round((12.0 + 0.2 - y) * 40)
    assert tuple(image[py, px + 5]) == (235, 180, 20)
    blank = env.top_down_image(trajectory=[])
    assert blank.shape == image.shape
    headless = BrainNavEnv()
    try:
        assert headless.render() is None
    finally:
        headless.close()
