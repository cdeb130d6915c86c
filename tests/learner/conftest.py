"""A tiny deterministic grid-navigation env with the BrainNav interface (for fast tests).

The robot lives on an ``n x n`` grid, faces one of 4 headings, and has BrainNav's three
actions (forward, turn left, turn right). Reaching the goal corner gives +100, driving into
the border -100 (episode ends), every other step -1; ``reward_mode="rich"`` adds minus the
Manhattan distance to the goal. ``optimal_actions()`` and ``shortest_path_steps`` come from
a breadth-first search, like the real env's oracle.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from services.learner.networks import ObsNormalizer
from services.learner.ppo import PPOConfig

torch.set_num_threads(1)  # tiny networks: threads only add contention

TOY_ENV_ID = "LearnerToyGrid-v0"
_MOVES = ((1, 0), (0, 1), (-1, 0), (0, -1))  # heading 0 = +x, counter-clockwise


class ToyGridEnv(gym.Env):
    """Grid navigation with BrainNav's action set and info keys."""

    def __init__(self, size: int = 5, reward_mode: str = "sparse", vary_start: bool = False):
        self.size = size
        self.reward_mode = reward_mode
        self.vary_start = vary_start
        self.goal = (size - 1, size - 1)
        self.action_space = spaces.Discrete(3)
        self.observation_space = spaces.Box(
            low=np.array([0, 0, 0, -1, -1], dtype=np.float32),
            high=np.array([size - 1, size - 1, 3, 1, 1], dtype=np.float32),
        )
        self._cost = self._search()
        self.state = (0, 0, 0)

    def _next(self, state: tuple[int, int, int], action: int) -> tuple[int, int, int] | None:
        x, y, h = state
        if action == 0:
            dx, dy = _MOVES[h]
            nx, ny = x + dx, y + dy
            if not (0 <= nx < self.size and 0 <= ny < self.size):
                return None
            return nx, ny, h
        return x, y, (h + (1 if action == 1 else -1)) % 4

    def _search(self) -> dict[tuple[int, int, int], int]:
        states = [(x, y, h) for x in range(self.size) for y in range(self.size) for h in range(4)]
        cost = {s: 0 for s in states if s[:2] == self.goal}
        frontier = deque(cost)
        while frontier:  # reverse BFS: predecessors of already-costed states
            target = frontier.popleft()
            for s in states:
                if s not in cost and any(self._next(s, a) == target for a in range(3)):
                    cost[s] = cost[target] + 1
                    frontier.append(s)
        return cost

    def _obs(self) -> np.ndarray:
        x, y, h = self.state
        dx, dy = _MOVES[h]
        return np.array([x, y, h, dx, dy], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        start_h = int(self.np_random.integers(0, 4)) if self.vary_start else 0
        self.state = (0, 0, start_h)
        return self._obs(), {
            "shortest_path_steps": self._cost[self.state],
            "pose": self.state,
            "is_success": False,
        }

    @staticmethod
    def observation_cell(obs: np.ndarray, size_m: float) -> tuple[int, int, int]:
        """The grid cell and heading of an observation (the exploration bonus's count)."""
        return int(obs[0] // size_m), int(obs[1] // size_m), int(obs[2])

    def optimal_actions(self) -> frozenset[int]:
        best = self._cost[self.state]
        return frozenset(
            a
            for a in range(3)
            if (n := self._next(self.state, a)) is not None and self._cost[n] == best - 1
        )

    def step(self, action: int):
        nxt = self._next(self.state, int(action))
        collision = nxt is None
        if not collision:
            self.state = nxt
        success = not collision and self.state[:2] == self.goal
        reward = -100.0 if collision else (100.0 if success else -1.0)
        if self.reward_mode == "rich":
            reward -= abs(self.goal[0] - self.state[0]) + abs(self.goal[1] - self.state[1])
        info = {"is_success": success, "collision": collision, "pose": self.state}
        return self._obs(), reward, success or collision, False, info


if TOY_ENV_ID not in gym.registry:
    gym.register(TOY_ENV_ID, entry_point=ToyGridEnv, max_episode_steps=30)


def toy_config(env_id: str = TOY_ENV_ID, **overrides: Any) -> PPOConfig:
    """A short sparse-reward PPO run on ``env_id`` (the toy grid by default): 1024 steps,
    4 epochs, an evaluation every 256 steps from one start; ``overrides`` change it."""
    base = PPOConfig(
        env_id=env_id,
        env_kwargs={"reward_mode": "sparse"},
        total_steps=1024,
        n_epochs=4,
        eval_every=256,
        eval_seeds=(0,),
    )
    return replace(base, **overrides)


def box_normalizer(n_obs: int = 3) -> ObsNormalizer:
    """Fhat's fixed normalisation for observations in [-1, 1]^n_obs (toy stage-2 tests)."""
    space = gym.spaces.Box(low=-np.ones(n_obs, np.float32), high=np.ones(n_obs, np.float32))
    return ObsNormalizer.from_space(space)


@pytest.fixture
def toy_env_id() -> str:
    """Gymnasium id of the toy grid env."""
    return TOY_ENV_ID
