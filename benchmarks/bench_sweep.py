"""``bgrl bench sweep``: one sweep of runs three ways in one process, one thread.

The sweep is the shape of the paper's Fig. 3 (``bgrl reproduce`` defaults): per seed, SSSG
and VSSG x (RL-sparse, RL-rich, HF+sparse at C = 0.55, 0.6, 0.7), 10 runs a seed, at a
reduced budget of env steps per run. Stage 2 (each HF+sparse run's pi_HF from 1000
simulated labels) is timed two ways: each run's alone (:func:`~services.learner.runs.
run_guidance`, the single path's) and all in lockstep (:func:`~services.learner.runs.
run_guidances`, the lockstep path's; its pi_HF must equal the single ones, checked here),
and each CPU time is added to its path's; then stage 3 is run

1. **single**: each run alone, one after the other (:func:`services.learner.runs.run_one`,
   the path of ``bgrl reproduce --single-run``);
2. **lockstep**: all runs in one batch (:func:`services.learner.runs.run_lockstep`, the
   path ``bgrl reproduce`` takes by default); its records must equal the single path's
   (checked here too, timings aside);
3. **sb3**: Stable-Baselines3 PPO on the same env (``make_vec_env``, one env as ours), the
   same network (separate 64-64 tanh actor and critic) and rollout settings (128 steps,
   64 epochs, minibatch 64, lr 3e-4, the same clip, coefficients and grad-norm clip), for
   the first ``sb3_runs`` RL runs of the sweep (SB3 has no pi_HF guidance; it is ~3x
   slower than our single path, so a few runs give its rate).

Figures per way, from process CPU time (robust on a shared machine) and wall time: runs
per CPU-hour and env steps (of RL, stage 3) per CPU-second, stage 2 included, and
stage-3-only env steps per CPU-second; the ratios lockstep/single and lockstep/sb3; the
full Fig. 3 (100 runs x 40,000 steps) extrapolated on 2 cores from the per-step and
per-pi_HF costs. The peak resident memory of each way is sampled while it runs.
"""

from __future__ import annotations

import os
import platform
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from datetime import UTC, datetime
from typing import Any

import torch

from services.learner.ppo import PPOConfig
from services.learner.runs import (
    RunGuidance,
    RunRecord,
    run_guidance,
    run_guidances,
    run_lockstep,
    run_one,
)
from services.learner.specs import RunSpec, build_specs

Progress = Callable[[str], None]
PARTS = 5
"""Parts :func:`run` reports through ``progress``, one call as each begins: stage 2 alone,
stage 2 in lockstep, the runs alone, in lockstep, and SB3's."""
FIG3_RUNS = 100
FIG3_STEPS = 40_000
CORES = 2


class PeakMemory:
    """Peak resident set size of this process while the ``with`` block runs (sampled every
    50 ms from /proc/self/statm)."""

    def __init__(self) -> None:
        self.start_bytes = 0
        self.peak_bytes = 0
        self._stop = threading.Event()
        self._page = os.sysconf("SC_PAGE_SIZE")

    def _rss(self) -> int:
        with open("/proc/self/statm") as statm:
            return int(statm.read().split()[1]) * self._page

    def _sample(self) -> None:
        while not self._stop.wait(0.05):
            self.peak_bytes = max(self.peak_bytes, self._rss())

    @contextmanager
    def watch(self) -> Iterator[PeakMemory]:
        """Sample during the block."""
        self.start_bytes = self.peak_bytes = self._rss()
        self._stop.clear()
        sampler = threading.Thread(target=self._sample, daemon=True)
        sampler.start()
        try:
            yield self
        finally:
            self._stop.set()
            sampler.join()
            self.peak_bytes = max(self.peak_bytes, self._rss())


@contextmanager
def _timed(into: dict[str, float]) -> Iterator[None]:
    wall, cpu = time.perf_counter(), time.process_time()
    yield
    into["wall_seconds"] = time.perf_counter() - wall
    into["cpu_seconds"] = time.process_time() - cpu


def sweep_specs(seeds: int, steps: int, labels: int = 1000) -> list[RunSpec]:
    """The Fig. 3 sweep of ``bgrl reproduce`` (defaults) for ``seeds`` seeds at ``steps``."""
    return build_specs(seeds=seeds, ppo_overrides={"total_steps": steps}, n_labels=labels)


def _sb3_run(spec: RunSpec) -> int:
    """SB3 PPO at our settings on the run's env; the env steps it took."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    config = spec.ppo_config()
    env = make_vec_env(config.env_id, n_envs=1, seed=spec.seed, env_kwargs=config.env_kwargs)
    try:
        model = PPO(
            "MlpPolicy",
            env,
            learning_rate=config.learning_rate,
            n_steps=config.n_steps,
            batch_size=config.minibatch_size,
            n_epochs=config.n_epochs,
            gamma=config.gamma,
            gae_lambda=config.gae_lambda,
            clip_range=config.clip_coef,
            ent_coef=config.ent_coef,
            vf_coef=config.vf_coef,
            max_grad_norm=config.max_grad_norm,
            policy_kwargs={"net_arch": {"pi": [64, 64], "vf": [64, 64]}},
            seed=spec.seed,
            device="cpu",
            verbose=0,
        )
        model.learn(total_timesteps=config.total_steps)
        return int(model.num_timesteps)
    finally:
        env.close()


def _rates(way: dict[str, Any], n_runs: int, env_steps: int, stage2_cpu: float) -> None:
    """Rates of a way whose timed part trained ``n_runs`` runs for ``env_steps`` steps,
    with the ``stage2_cpu`` seconds that learning their pi_HF took added (measured once)."""
    stage3_cpu = way["cpu_seconds"]
    cpu = stage3_cpu + stage2_cpu
    way |= {
        "runs": n_runs,
        "env_steps": env_steps,
        "stage2_cpu_seconds": stage2_cpu,
        "runs_per_cpu_hour": n_runs / cpu * 3600,
        "env_steps_per_cpu_second": env_steps / cpu,
        "stage3_env_steps_per_cpu_second": env_steps / stage3_cpu,
        "stage3_env_steps_per_second": env_steps / way["wall_seconds"],
    }


def _same_guidance(a: Sequence[RunGuidance], b: Sequence[Any]) -> bool:
    """Equal pi_HF (Fhat's weights), SPL and stage-2 summary (wall time aside)."""

    def comparable(guidance: RunGuidance) -> tuple[Any, ...]:
        summary = {**(guidance.summary or {}), "wall_seconds": None}
        weights = [w.tolist() for w in guidance.policy.model.state_dict().values()]
        return guidance.spl, summary, weights

    return all(isinstance(g, RunGuidance) for g in b) and [comparable(g) for g in a] == [
        comparable(g) for g in b
    ]


def _same_records(a: Sequence[RunRecord], b: Sequence[Any]) -> bool:
    def comparable(record: Any) -> dict[str, Any]:
        data = record.to_dict()
        data["wall_seconds"] = None
        if data.get("hf"):
            data["hf"] = {**data["hf"], "wall_seconds": None}
        return data

    return all(isinstance(r, RunRecord) for r in b) and [comparable(r) for r in a] == [
        comparable(r) for r in b
    ]


def run(
    *,
    seeds: int = 2,
    steps: int = 4096,
    sb3_runs: int = 2,
    labels: int = 1000,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Measure the sweep of ``seeds`` seeds x 10 runs at ``steps`` env steps three ways
    (HF+sparse runs learning pi_HF from ``labels`` labels)."""
    torch.set_num_threads(1)
    say = progress or (lambda message: None)
    specs = sweep_specs(seeds, steps, labels)
    started = datetime.now(UTC).isoformat(timespec="seconds")
    load_before = os.getloadavg()
    for task in ("sssg", "vssg"):  # warm-up: the oracle's disk cache, imports
        run_one(RunSpec(task, "rl_sparse", 0, ppo_overrides={"total_steps": 128}))
    hf_specs = [s for s in specs if s.method == "hf_sparse"]
    stage2: dict[str, float] = {}
    say(f"stage 2 alone: {len(hf_specs)} pi_HF")
    with _timed(stage2):
        alone = [run_guidance(spec) for spec in hf_specs]
    stage2_lockstep: dict[str, Any] = {}
    say(f"stage 2 in lockstep: {len(hf_specs)} pi_HF")
    with _timed(stage2_lockstep):
        together = run_guidances(hf_specs)
    stage2_lockstep["guidance_equal_single"] = _same_guidance(alone, together)
    learned = iter([guidance.policy for guidance in alone])
    policies = [next(learned) if s.method == "hf_sparse" else None for s in specs]
    ways: dict[str, dict[str, Any]] = {}
    memory = PeakMemory()

    say(f"single: {len(specs)} runs alone")
    ways["single"] = {}
    with memory.watch(), _timed(ways["single"]):
        single = [
            run_one(spec, hf_policy=policy) for spec, policy in zip(specs, policies, strict=True)
        ]
    ways["single"]["peak_rss_bytes"] = memory.peak_bytes
    env_steps = sum(spec.ppo_config().total_steps for spec in specs)
    _rates(ways["single"], len(specs), env_steps, stage2["cpu_seconds"])

    say(f"lockstep: {len(specs)} runs in one batch")
    ways["lockstep"] = {}
    with memory.watch(), _timed(ways["lockstep"]):
        batched = run_lockstep(specs, hf_policies=policies)
    ways["lockstep"]["peak_rss_bytes"] = memory.peak_bytes
    ways["lockstep"]["rss_before_bytes"] = memory.start_bytes
    _rates(ways["lockstep"], len(specs), env_steps, stage2_lockstep["cpu_seconds"])
    ways["lockstep"]["records_equal_single"] = _same_records(single, batched)

    rl_specs = [s for s in specs if s.method != "hf_sparse"][:sb3_runs]
    say(f"sb3: {len(rl_specs)} runs")
    ways["sb3"] = {}
    with memory.watch(), _timed(ways["sb3"]):
        sb3_steps = sum(_sb3_run(spec) for spec in rl_specs)
    ways["sb3"]["peak_rss_bytes"] = memory.peak_bytes
    _rates(ways["sb3"], len(rl_specs), sb3_steps, 0.0)

    lockstep, single_way, sb3 = ways["lockstep"], ways["single"], ways["sb3"]
    figures = {
        "lockstep_vs_single_runs_per_cpu_hour": lockstep["runs_per_cpu_hour"]
        / single_way["runs_per_cpu_hour"],
        "lockstep_vs_single_stage3_env_steps_per_cpu_second": lockstep[
            "stage3_env_steps_per_cpu_second"
        ]
        / single_way["stage3_env_steps_per_cpu_second"],
        "lockstep_vs_sb3_env_steps_per_cpu_second": lockstep["env_steps_per_cpu_second"]
        / sb3["env_steps_per_cpu_second"],
        "lockstep_vs_sb3_stage3_env_steps_per_cpu_second": lockstep[
            "stage3_env_steps_per_cpu_second"
        ]
        / sb3["env_steps_per_cpu_second"],
        "lockstep_records_equal_single": lockstep["records_equal_single"],
        "lockstep_vs_single_stage2_cpu": stage2["cpu_seconds"] / stage2_lockstep["cpu_seconds"],
        "lockstep_stage2_equal_single": stage2_lockstep["guidance_equal_single"],
        **_fig3_extrapolation(lockstep, single_way, stage2, stage2_lockstep, specs),
    }
    return {
        "name": "sweep",
        "started_utc": started,
        "figures": figures,
        "ways": ways,
        "stage2_alone": stage2 | {"hf_runs": len(hf_specs)},
        "stage2_lockstep": stage2_lockstep | {"hf_runs": len(hf_specs)},
        "settings": {
            "seeds": seeds,
            "runs": len(specs),
            "steps_per_run": steps,
            "sb3_runs": len(rl_specs),
            "ppo": {k: getattr(PPOConfig(), k) for k in ("n_steps", "n_epochs", "minibatch_size")},
            "torch_threads": torch.get_num_threads(),
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        },
    }


def _fig3_extrapolation(
    lockstep: dict[str, Any],
    single: dict[str, Any],
    stage2: dict[str, float],
    stage2_lockstep: dict[str, float],
    specs: Sequence[RunSpec],
) -> dict[str, float]:
    """Fig. 3 (100 runs x 40k steps, 60 of them HF+sparse) on 2 cores, from this sweep's
    per-step stage-3 cost and per-run stage-2 cost of each path, and the peak memory of a
    100-run batch (linear in runs from this batch's growth over the process's size before
    it)."""
    n_hf = sum(s.method == "hf_sparse" for s in specs)
    fig3_hf = FIG3_RUNS * n_hf / len(specs)
    fig3_steps = FIG3_RUNS * FIG3_STEPS
    out = {}
    for name, way, learning in (
        ("lockstep", lockstep, stage2_lockstep),
        ("single", single, stage2),
    ):
        stage2_per_hf = learning["cpu_seconds"] / max(n_hf, 1)
        stage3_per_step = way["cpu_seconds"] / way["env_steps"]
        cpu = stage3_per_step * fig3_steps + stage2_per_hf * fig3_hf
        out[f"fig3_{name}_cpu_minutes_extrapolated"] = cpu / 60
        out[f"fig3_{name}_wall_minutes_on_{CORES}_cores_extrapolated"] = cpu / 60 / CORES
    per_run = (lockstep["peak_rss_bytes"] - lockstep["rss_before_bytes"]) / len(specs)
    base = lockstep["rss_before_bytes"]
    out["fig3_lockstep_peak_rss_one_process_bytes_extrapolated"] = base + per_run * FIG3_RUNS
    out[f"fig3_lockstep_peak_rss_{CORES}_workers_bytes_extrapolated"] = CORES * (
        base + per_run * FIG3_RUNS / CORES
    )
    return out
