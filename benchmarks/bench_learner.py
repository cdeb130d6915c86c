"""Learner benchmark: PPO throughput vs Stable-Baselines3, Fhat update rate, time to 0.7 SPL.

Every figure is measured against a peer in the same process:

* ``ppo_steps_per_second`` of our PPO vs SB3 PPO on the same env (BrainNav SSSG, sparse),
  same network (separate 64-64 tanh actor and critic), same rollout settings (128 steps,
  64 epochs, minibatch 64, lr 3e-4), single thread: ratio ``ours / sb3``, in wall-clock and
  in process CPU time (the robust figure on a shared machine).
* ``fhat_labels_per_second`` with K_HF replay updates per label, against the same learner
  with K_HF = 0 (the cost of a single SGD step per label).
* ``time_to_spl_0_7`` of HF+sparse (C = 0.7, stage 2 included) against RL-sparse on VSSG
  (the task of the paper's real-EEG experiment) for the same seeds, each run stopped when
  its greedy policy first reaches SPL 0.7 or at the budget: env steps and wall seconds per
  run, and the medians over the runs that reached it.

Run: ``bgrl bench learner --out DIR`` (writes ``DIR/learner.json``).
"""

from __future__ import annotations

import platform
import time
from contextlib import closing
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from services.core.files import write_results_json
from services.learner.feedback import (
    FeedbackConfig,
    FeedbackLearner,
)
from services.learner.networks import ObsNormalizer
from services.learner.ppo import Callback, PPOConfig, train
from services.learner.runs import SPL_TARGET, learn_hf_policy
from services.learner.specs import RunSpec

ENV_ID = "services.sim:BrainNav-SSSG-v0"
TARGET_TASK = "vssg"


def _ppo_throughput_ours(steps: int) -> tuple[float, float]:
    config = PPOConfig(env_id=ENV_ID, total_steps=steps, eval_every=10 * steps)
    start, cpu_start = time.perf_counter(), time.process_time()
    train(config)
    return steps / (time.perf_counter() - start), steps / (time.process_time() - cpu_start)


def _ppo_throughput_sb3(steps: int) -> tuple[float, float]:
    from stable_baselines3 import PPO

    start, cpu_start = time.perf_counter(), time.process_time()  # env construction included
    with closing(gym.make(ENV_ID, reward_mode="sparse")) as env:
        model = PPO(
            "MlpPolicy",
            env,
            learning_rate=3e-4,
            n_steps=128,
            batch_size=64,
            n_epochs=64,
            gamma=0.99,
            gae_lambda=0.95,
            clip_range=0.2,
            ent_coef=0.02,
            vf_coef=0.5,
            max_grad_norm=25.0,
            policy_kwargs={"net_arch": {"pi": [64, 64], "vf": [64, 64]}},
            seed=0,
            device="cpu",
            verbose=0,
        )
        model.learn(total_timesteps=steps)
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu_start
    return steps / elapsed, steps / cpu


def _fhat_rate(n_labels: int, replay_updates: int) -> float:
    space = gym.spaces.Box(low=np.zeros(13, np.float32), high=np.full(13, 13.0, np.float32))
    learner = FeedbackLearner(
        ObsNormalizer.from_space(space), FeedbackConfig(replay_updates=replay_updates), seed=0
    )
    rng = np.random.default_rng(0)
    obs = rng.uniform(0, 13, size=(n_labels, 13)).astype(np.float32)
    actions = rng.integers(0, 3, n_labels)
    labels = rng.random(n_labels) < 0.5
    start = time.perf_counter()
    for i in range(n_labels):
        learner.add(obs[i], int(actions[i]), bool(labels[i]))
    return n_labels / (time.perf_counter() - start)


class _StopAtTarget(Callback):
    def __init__(self) -> None:
        self.reached_at: int | None = None

    def on_eval(self, global_step: int, spl: float) -> bool:
        if spl >= SPL_TARGET and self.reached_at is None:
            self.reached_at = global_step
        return self.reached_at is None


def _time_to_target(method: str, seed: int, total_steps: int) -> dict[str, Any]:
    spec = RunSpec(
        TARGET_TASK,
        method,
        seed,
        accuracy=0.7 if method == "hf_sparse" else None,
        ppo_overrides={"total_steps": total_steps},
    )
    config = spec.ppo_config()
    start = time.perf_counter()
    hf_policy = None
    if method == "hf_sparse":
        with closing(gym.make(config.env_id, **config.env_kwargs)) as env:
            hf_policy = learn_hf_policy(env, 0.7, seed, spec.n_labels).policy
    stopper = _StopAtTarget()
    result = train(config, stopper, hf_policy=hf_policy)
    return {
        "method": method,
        "seed": seed,
        "env_steps_to_0_7": stopper.reached_at,
        "wall_seconds": time.perf_counter() - start,
        "env_steps_run": result.global_step,
    }


def _median_reached(runs: list[dict[str, Any]], key: str) -> float | None:
    reached = [r[key] for r in runs if r["env_steps_to_0_7"] is not None]
    return float(np.median(reached)) if reached else None


def run_benchmark(
    out_dir: str | Path, *, steps: int = 4096, target_steps: int = 40_000, target_seeds: int = 3
) -> dict[str, Any]:
    """Measure everything and write ``out_dir/learner.json``.

    ``steps`` env steps per throughput measurement; ``target_steps`` is the budget of the
    time-to-0.7 runs (each stops as soon as its greedy policy reaches SPL 0.7), run for
    seeds ``0 .. target_seeds - 1`` of each method.
    """
    torch.set_num_threads(1)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    gym.make(ENV_ID).close()  # warm-up: builds the oracle's disk cache once
    ours, ours_cpu = _ppo_throughput_ours(steps)
    sb3, sb3_cpu = _ppo_throughput_sb3(steps)
    fhat = _fhat_rate(300, FeedbackConfig().replay_updates)
    fhat_single = _fhat_rate(300, 0)
    hf_runs = [_time_to_target("hf_sparse", s, target_steps) for s in range(target_seeds)]
    rl_runs = [_time_to_target("rl_sparse", s, target_steps) for s in range(target_seeds)]
    figures = {
        "ppo_steps_per_second": ours,
        "sb3_ppo_steps_per_second": sb3,
        "ppo_speedup_vs_sb3": ours / sb3,
        "ppo_steps_per_cpu_second": ours_cpu,
        "sb3_ppo_steps_per_cpu_second": sb3_cpu,
        "ppo_speedup_vs_sb3_cpu_time": ours_cpu / sb3_cpu,
        "fhat_labels_per_second_k_hf": fhat,
        "fhat_k_hf": FeedbackConfig().replay_updates,
        "fhat_labels_per_second_k0": fhat_single,
        "hf_sparse_c0_7_runs_reaching_0_7": sum(r["env_steps_to_0_7"] is not None for r in hf_runs),
        "hf_sparse_c0_7_median_steps_to_0_7": _median_reached(hf_runs, "env_steps_to_0_7"),
        "hf_sparse_c0_7_median_seconds_to_0_7": _median_reached(hf_runs, "wall_seconds"),
        "rl_sparse_runs_reaching_0_7": sum(r["env_steps_to_0_7"] is not None for r in rl_runs),
        "rl_sparse_median_steps_to_0_7": _median_reached(rl_runs, "env_steps_to_0_7"),
        "rl_sparse_median_seconds_to_0_7": _median_reached(rl_runs, "wall_seconds"),
        "time_to_target_runs_per_method": target_seeds,
    }
    result = {
        "name": "learner",
        "figures": figures,
        "runs": hf_runs + rl_runs,
        "settings": {
            "throughput_steps": steps,
            "time_to_target_budget_steps": target_steps,
            "time_to_target_task": TARGET_TASK,
            "env": ENV_ID,
            "torch_threads": torch.get_num_threads(),
            "python": platform.python_version(),
            "torch": torch.__version__,
        },
    }
    write_results_json(out / "learner.json", result, indent=1)
    return result
