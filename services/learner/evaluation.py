"""SPL evaluation of a greedy policy on fixed evaluation starts.

SPL (Anderson et al. 2018) is the mean over episodes of ``S_i * l_i / max(p_i, l_i)`` with
``l_i`` the oracle's shortest path and ``p_i`` the path taken, both counted in actions.
The evaluation starts are fixed by reset seeds: SSSG has one start (any seed), VSSG draws
its jittered start from the reset seed, so a fixed tuple of seeds is a fixed set of starts.
They come from their own fixed stream (:func:`services.learner.seeding.evaluation_reset_seeds`),
which no run's training, label collection or label noise can produce.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np

from services.learner.seeding import evaluation_reset_seeds
from services.sim.metrics import spl


def eval_seeds(task: str, n_starts: int = 5) -> tuple[int, ...]:
    """The fixed evaluation starts of a task: one for SSSG, ``n_starts`` for VSSG."""
    if task == "sssg":
        return evaluation_reset_seeds(1)
    if task == "vssg":
        return evaluation_reset_seeds(n_starts)
    raise ValueError(f"unknown task {task!r}; expected 'sssg' or 'vssg'")


def run_episode(
    env: gym.Env, act: Callable[[np.ndarray], int], seed: int
) -> tuple[bool, int, int, list[tuple[float, float, float]]]:
    """Run one greedy episode from ``reset(seed=seed)``.

    Returns
    -------
    success, shortest_steps, taken_steps, poses
    """
    obs, info = env.reset(seed=seed)
    shortest = int(info["shortest_path_steps"])
    poses = [tuple(info["pose"])] if "pose" in info else []
    taken = 0
    while True:
        obs, _, terminated, truncated, info = env.step(act(obs))
        taken += 1
        if "pose" in info:
            poses.append(tuple(info["pose"]))
        if terminated or truncated:
            return bool(info.get("is_success", False)), shortest, taken, poses


def evaluate_spl(env: gym.Env, act: Callable[[np.ndarray], int], seeds: Sequence[int]) -> float:
    """SPL of ``act`` over one episode per evaluation seed."""
    episodes = [run_episode(env, act, seed)[:3] for seed in seeds]
    successes, shortest, taken = zip(*episodes, strict=True)
    return float(spl(list(successes), list(shortest), list(taken)))
