"""Navigation metrics: SPL (Anderson et al. 2018) and the random-policy success rate."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from services.core.actions import N_ACTIONS, Action


def spl(
    successes: Sequence[bool], shortest_steps: Sequence[int], taken_steps: Sequence[int]
) -> float:
    """Success weighted by (normalised inverse) Path Length, counted in actions.

    ``SPL = mean_i S_i * l_i / max(p_i, l_i)`` (Anderson et al., "On Evaluation of Embodied
    Navigation Agents", 2018), with ``S_i`` the success of episode ``i``, ``l_i`` its
    shortest path (the oracle's ``shortest_path_steps`` for that start) and ``p_i`` the
    number of actions taken.

    Raises
    ------
    ValueError
        The sequences are empty or differ in length, a shortest path is not positive, or a
        taken path is negative.
    """
    s = np.asarray(successes, dtype=bool)
    lengths = np.asarray(shortest_steps, dtype=np.float64)
    taken = np.asarray(taken_steps, dtype=np.float64)
    if s.ndim != 1 or s.shape != lengths.shape or s.shape != taken.shape:
        raise ValueError(
            "successes, shortest_steps and taken_steps must be 1-D and of equal length, got "
            f"{s.shape}, {lengths.shape}, {taken.shape}"
        )
    if s.size == 0:
        raise ValueError("SPL needs at least one episode")
    if np.any(lengths <= 0):
        raise ValueError("every shortest path must be at least one action")
    if np.any(taken < 0):
        raise ValueError("taken path lengths cannot be negative")
    return float(np.mean(s * lengths / np.maximum(taken, lengths)))


@dataclass(frozen=True)
class RandomPolicyResult:
    """Outcome of uniformly random episodes on one map and task."""

    episodes: int
    successes: int
    collisions: int
    success_rate: float
    collision_rate: float


def random_policy_success_rate(
    task: str = "vssg",
    *,
    episodes: int = 10_000,
    seed: int = 0,
    map_path: str | Path | None = None,
    progress: bool = False,
    oracle_cache_dir: str | Path | None = None,
) -> RandomPolicyResult:
    """Run a uniformly random policy through the real env for 120-step episodes.

    The paper's premise is that random exploration rarely finds the sparse reward; the
    default map aims at about 0.1 % (see ``docs/sim.md``). ``oracle_cache_dir``: see
    :class:`services.sim.env.BrainNavEnv`.
    """
    return _walker_success_rate(
        lambda obs, rng: int(rng.integers(N_ACTIONS)),
        task,
        episodes=episodes,
        seed=seed,
        map_path=map_path,
        description="random episodes",
        progress=progress,
        oracle_cache_dir=oracle_cache_dir,
    )


def wall_averse_policy_success_rate(
    task: str = "vssg",
    *,
    episodes: int = 10_000,
    seed: int = 0,
    map_path: str | Path | None = None,
    forward_probability: float = 1.0 / 3.0,
    min_clearance: float = 1.0,
    central_rays: int = 4,
    progress: bool = False,
    oracle_cache_dir: str | Path | None = None,
) -> RandomPolicyResult:
    """Like :func:`random_policy_success_rate`, for a random walker that avoids walls.

    Each step: if any of the ``central_rays`` central ray distances (of the 10 over
    -90..+90 deg) is below ``min_clearance`` metres, turn left or right with equal
    probability; otherwise drive forward with probability ``forward_probability`` and turn
    left or right with equal probability otherwise (1/3 is the uniform walker's mix).

    This is what a sparse-reward learner tends to become first (the collision penalty is
    its only frequent signal), so it says how hard a map is for that learner more than the
    uniform walker does (``docs/reproduction.md``, ``docs/map-study.md``).
    """
    if not 0.0 <= forward_probability <= 1.0:
        raise ValueError(f"forward_probability must be in [0, 1], got {forward_probability}")
    if not 1 <= central_rays <= 10:
        raise ValueError(f"central_rays must be in 1..10, got {central_rays}")
    first = (10 - central_rays) // 2

    def wall_averse(obs: np.ndarray, rng: np.random.Generator) -> int:
        blocked = float(np.min(obs[first : first + central_rays])) < min_clearance
        if not blocked and rng.random() < forward_probability:
            return int(Action.FORWARD)
        return int(Action.TURN_LEFT if rng.random() < 0.5 else Action.TURN_RIGHT)

    return _walker_success_rate(
        wall_averse,
        task,
        episodes=episodes,
        seed=seed,
        map_path=map_path,
        description="wall-averse episodes",
        progress=progress,
        oracle_cache_dir=oracle_cache_dir,
    )


def _walker_success_rate(
    policy: Callable[[np.ndarray, np.random.Generator], int],
    task: str,
    *,
    episodes: int,
    seed: int,
    map_path: str | Path | None,
    description: str,
    progress: bool,
    oracle_cache_dir: str | Path | None,
) -> RandomPolicyResult:
    """Run ``policy(obs, rng)`` through the real env for 120-step episodes, reset seeds
    ``seed, seed + 1, ...``, and count successes and collisions."""
    from services.sim import MAX_EPISODE_STEPS
    from services.sim.env import BrainNavEnv

    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    rng = np.random.default_rng(seed)
    env = BrainNavEnv(
        task=task,  # type: ignore[arg-type]
        map_path=map_path,
        oracle_cache_dir=oracle_cache_dir,
    )
    successes = collisions = 0
    try:
        for episode in tqdm(range(episodes), desc=description, disable=not progress):
            obs, _ = env.reset(seed=seed + episode)
            for _ in range(MAX_EPISODE_STEPS):
                obs, _, terminated, _, info = env.step(policy(obs, rng))
                if terminated:
                    successes += info["is_success"]
                    collisions += info["collision"]
                    break
    finally:
        env.close()
    return RandomPolicyResult(
        episodes=episodes,
        successes=successes,
        collisions=collisions,
        success_rate=successes / episodes,
        collision_rate=collisions / episodes,
    )
