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

import json
import multiprocessing
import platform
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import closing
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import TransformReward

from services.core.files import write_results_json
from services.learner.evaluation import eval_seeds, evaluate_spl
from services.learner.ppo import PPOConfig
from services.learner.specs import N_VSSG_EVAL_STARTS, REWARD_MODES, TASK_ENV_IDS

SPL_TARGET = 0.7
REWARD_SCALE = PPOConfig().reward_scale
"""The reward scale of our PPO (0.01), applied to SB3's rewards too: one factor less."""
Progress = Callable[[str], None]


def sb3_run(
    task: str,
    method: str,
    seed: int,
    total_steps: int,
    eval_every: int,
    stop_when_held: int | None = None,
    partial_path: Path | None = None,
    reward_scale: float = REWARD_SCALE,
) -> dict[str, Any]:
    """One SB3 PPO run (defaults) of ``method``'s reward on ``task``: its record.

    With ``stop_when_held`` the run stops once that many evaluations in a row reached
    SPL 0.7 (to spare CPU on a shared machine; the record says where it stopped). With
    ``partial_path`` the record so far (``"partial": true``) is written there after every
    evaluation, so a run cut short still shows its curve. SB3 sees the env's rewards times
    ``reward_scale`` (default: our PPO's, so that both learners see the same rewards).
    """
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env

    env_kwargs = {"reward_mode": REWARD_MODES[method]}
    env_id = TASK_ENV_IDS[task]
    starts = eval_seeds(task, N_VSSG_EVAL_STARTS)
    curve: list[list[float]] = []
    torch.set_num_threads(1)
    started = time.perf_counter()

    def record(*, partial: bool) -> dict[str, Any]:
        reached = [steps for steps, value in curve if value >= SPL_TARGET]
        return {
            "task": task,
            "method": method,
            "reward_mode": env_kwargs["reward_mode"],
            "learner": "sb3_ppo_defaults",
            "seed": seed,
            "total_steps": total_steps,
            "eval_every": eval_every,
            "stop_when_held": stop_when_held,
            "reward_scale": reward_scale,
            "stopped_at": None if partial or curve[-1][0] >= total_steps else curve[-1][0],
            "partial": partial,
            "curve": curve,
            "final_spl": curve[-1][1],
            "last5_spl": sum(v for _, v in curve[-5:]) / len(curve[-5:]),
            "steps_to_0_7": reached[0] if reached else None,
            "wall_seconds": time.perf_counter() - started,
        }

    env = make_vec_env(
        env_id,
        n_envs=1,
        seed=seed,
        env_kwargs=env_kwargs,
        wrapper_class=TransformReward,
        wrapper_kwargs={"func": lambda reward: reward_scale * reward},
    )
    with closing(gym.make(env_id, reward_mode="sparse")) as eval_env:

        def evaluate(model: PPO) -> None:
            def act(obs: Any) -> int:
                return int(model.predict(obs, deterministic=True)[0])

            curve.append([int(model.num_timesteps), evaluate_spl(eval_env, act, starts)])
            if partial_path is not None:
                write_results_json(partial_path, record(partial=True), indent=None)

        class Evaluate(BaseCallback):
            def _on_step(self) -> bool:
                if self.num_timesteps % eval_every == 0:
                    evaluate(self.model)
                    held = [v for _, v in curve[-(stop_when_held or 0) :]]
                    if stop_when_held and len(held) == stop_when_held:
                        return min(held) < SPL_TARGET
                return True

        try:
            model = PPO("MlpPolicy", env, seed=seed, device="cpu", verbose=0)
            evaluate(model)
            model.learn(total_timesteps=total_steps, callback=Evaluate())
        finally:
            env.close()
    return record(partial=False)


def _key(record: dict[str, Any]) -> tuple[str, str, int]:
    return (record["task"], record["method"], int(record["seed"]))


def _settings(record: dict[str, Any]) -> tuple[Any, ...]:
    return (
        record["total_steps"],
        record.get("stop_when_held"),
        record.get("eval_every"),
        record.get("reward_scale"),
    )


def summarize(runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (task, method): seeds, final and last-5 SPL mean and std, runs reaching 0.7,
    median steps to 0.7."""
    rows = []
    for task, method in sorted({(r["task"], r["method"]) for r in runs}):
        group = [r for r in runs if (r["task"], r["method"]) == (task, method)]
        final = np.array([r["final_spl"] for r in group])
        last5 = np.array([r["last5_spl"] for r in group])
        reached = [r["steps_to_0_7"] for r in group if r["steps_to_0_7"] is not None]
        rows.append(
            {
                "task": task,
                "method": method,
                "reward_mode": group[0]["reward_mode"],
                "seeds": sorted(int(r["seed"]) for r in group),
                "final_spl_mean": float(final.mean()),
                "final_spl_std": float(final.std()),
                "last5_spl_mean": float(last5.mean()),
                "last5_spl_std": float(last5.std()),
                "runs_reaching_0_7": len(reached),
                "median_steps_to_0_7": float(np.median(reached)) if reached else None,
                "stopped_early": sum(r["stopped_at"] is not None for r in group),
            }
        )
    return rows


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    """The summary rows as a Markdown table."""
    lines = [
        "| task | method (reward) | seeds | final SPL | last-5 SPL | runs reaching 0.7 "
        "| median steps to 0.7 | stopped early |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        median = "-" if r["median_steps_to_0_7"] is None else f"{r['median_steps_to_0_7']:.0f}"
        n = len(r["seeds"])
        lines.append(
            f"| {r['task'].upper()} | {r['method']} ({r['reward_mode']}) | {n} | "
            f"{r['final_spl_mean']:.2f} ± {r['final_spl_std']:.2f} | "
            f"{r['last5_spl_mean']:.2f} ± {r['last5_spl_std']:.2f} | "
            f"{r['runs_reaching_0_7']}/{n} | {median} | {r['stopped_early']}/{n} |"
        )
    return "\n".join(lines) + "\n"


def plot_curves(runs: list[dict[str, Any]], out: Path) -> list[Path]:
    """``sb3_peer_<task>.png``: every run's SPL curve (one line a seed) per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for task in sorted({r["task"] for r in runs}):
        fig, ax = plt.subplots(figsize=(7, 4.5))
        methods = sorted({r["method"] for r in runs if r["task"] == task})
        for index, method in enumerate(methods):
            group = sorted(
                (r for r in runs if (r["task"], r["method"]) == (task, method)),
                key=lambda r: r["seed"],
            )
            for j, r in enumerate(group):
                steps, spl = zip(*r["curve"], strict=True)
                label = f"{method} ({r['reward_mode']}), n={len(group)}" if j == 0 else None
                ax.plot(steps, spl, color=f"C{index}", alpha=0.6, label=label, marker=".")
        ax.set_title(f"{task.upper()}: SB3 PPO (defaults), greedy SPL, one line a seed")
        ax.set_xlabel("environment steps")
        ax.set_ylabel("SPL")
        ax.set_ylim(-0.02, 1.1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
        fig.tight_layout()
        path = out / f"sb3_peer_{task}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def run(
    out: Path,
    *,
    tasks: list[str],
    methods: list[str],
    seeds: list[int],
    total_steps: int,
    eval_every: int,
    stop_when_held: int | None,
    workers: int,
    reward_scale: float = REWARD_SCALE,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Every (task, method, seed) run not yet in ``out/sb3_peer.json`` (runs there with
    other settings are refused), ``workers`` at a time in spawned processes; the file is
    rewritten after each run, then ``summary.md`` and the plots. Returns the document."""
    import stable_baselines3

    for method in methods:
        if method not in REWARD_MODES:
            raise ValueError(f"unknown method {method!r}; expected one of {list(REWARD_MODES)}")
    path = out / "sb3_peer.json"
    runs: list[dict[str, Any]] = json.loads(path.read_text())["runs"] if path.exists() else []
    wanted = (total_steps, stop_when_held, eval_every, reward_scale)
    if any(_settings(r) != wanted for r in runs):
        raise ValueError(f"{path} holds runs with other settings; use another --out")
    done = {_key(r) for r in runs}
    todo = [
        (task, method, seed)
        for task in tasks
        for method in methods
        for seed in seeds
        if (task, method, seed) not in done
    ]
    document = {
        "learner": "stable_baselines3.PPO('MlpPolicy') with its defaults",
        "stable_baselines3": stable_baselines3.__version__,
        "python": platform.python_version(),
        "runs": runs,
    }
    partial = out / "partial"  # each running run's curve so far
    partial.mkdir(exist_ok=True)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context) as pool:
        futures = [
            pool.submit(
                sb3_run,
                task,
                method,
                seed,
                total_steps,
                eval_every,
                stop_when_held,
                partial / f"{task}_{method}_{seed}.json",
                reward_scale,
            )
            for task, method, seed in todo
        ]
        for future in as_completed(futures):
            record = future.result()
            runs.append(record)
            runs.sort(key=_key)
            write_results_json(path, document, indent=1)
            if progress is not None:
                progress(
                    f"{record['task']} {record['method']} seed={record['seed']} "
                    f"final SPL {record['final_spl']:.2f}"
                )
    document["summary"] = summarize(runs)
    write_results_json(path, document, indent=1)
    (out / "summary.md").write_text(summary_markdown(document["summary"]))
    plot_curves(runs, out)
    return document
