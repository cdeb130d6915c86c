"""``bgrl bench sb3-peer``: Stable-Baselines3 PPO with its defaults on our env, SPL curves.

A peer learner for a reward: does a textbook PPO, untuned, learn the task from it? Each run
trains ``stable_baselines3.PPO("MlpPolicy", env)`` with every SB3 default (n_steps 2048,
batch 64, 10 epochs, lr 3e-4, gamma 0.99, GAE 0.95, no entropy bonus, no reward or
observation normalisation) on ``gymnasium.make(BrainNav-<task>-v0, reward_mode=...)`` and
evaluates its deterministic policy every ``eval_every`` steps with the SPL evaluation of
``bgrl reproduce`` (the same fixed starts: :func:`services.learner.evaluation.eval_seeds`).
The shaping discount of a shaped reward is SB3's gamma (0.99). The records carry the fields
of a ``bgrl reproduce`` run that apply (``task``, ``method``, ``seed``, ``curve``,
``final_spl``, ``steps_to_0_7``) plus ``learner: "sb3_ppo_defaults"`` and the reward.
"""

from __future__ import annotations

import platform
import time
from collections.abc import Callable
from contextlib import closing
from typing import Any

import gymnasium as gym

from services.learner.evaluation import eval_seeds, evaluate_spl
from services.learner.specs import N_VSSG_EVAL_STARTS, REWARD_MODES, TASK_ENV_IDS

SPL_TARGET = 0.7
Progress = Callable[[str], None]


def sb3_run(task: str, method: str, seed: int, total_steps: int, eval_every: int) -> dict[str, Any]:
    """One SB3 PPO run (defaults) of ``method``'s reward on ``task``: its record."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env

    env_kwargs = {"reward_mode": REWARD_MODES[method]}
    env_id = TASK_ENV_IDS[task]
    starts = eval_seeds(task, N_VSSG_EVAL_STARTS)
    curve: list[list[float]] = []
    started = time.perf_counter()
    env = make_vec_env(env_id, n_envs=1, seed=seed, env_kwargs=env_kwargs)
    with closing(gym.make(env_id, reward_mode="sparse")) as eval_env:

        def evaluate(model: PPO) -> None:
            def act(obs: Any) -> int:
                return int(model.predict(obs, deterministic=True)[0])

            curve.append([int(model.num_timesteps), evaluate_spl(eval_env, act, starts)])

        class Evaluate(BaseCallback):
            def _on_step(self) -> bool:
                if self.num_timesteps % eval_every == 0:
                    evaluate(self.model)
                return True

        try:
            model = PPO("MlpPolicy", env, seed=seed, device="cpu", verbose=0)
            evaluate(model)
            model.learn(total_timesteps=total_steps, callback=Evaluate())
        finally:
            env.close()
    reached = [steps for steps, value in curve if value >= SPL_TARGET]
    return {
        "task": task,
        "method": method,
        "reward_mode": env_kwargs["reward_mode"],
        "learner": "sb3_ppo_defaults",
        "seed": seed,
        "total_steps": total_steps,
        "curve": curve,
        "final_spl": curve[-1][1],
        "last5_spl": sum(v for _, v in curve[-5:]) / len(curve[-5:]),
        "steps_to_0_7": reached[0] if reached else None,
        "wall_seconds": time.perf_counter() - started,
    }


def run(
    *,
    tasks: list[str],
    methods: list[str],
    seeds: list[int],
    total_steps: int,
    eval_every: int,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every (task, method, seed) run in turn; the results document."""
    import stable_baselines3

    runs = []
    for task in tasks:
        for method in methods:
            for seed in seeds:
                runs.append(sb3_run(task, method, seed, total_steps, eval_every))
                if progress is not None:
                    last = runs[-1]
                    progress(f"{task} {method} seed={seed} final SPL {last['final_spl']:.2f}")
    return {
        "learner": "stable_baselines3.PPO('MlpPolicy') with its defaults",
        "stable_baselines3": stable_baselines3.__version__,
        "python": platform.python_version(),
        "runs": runs,
    }
