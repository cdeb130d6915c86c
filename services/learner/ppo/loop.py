"""``train(config, callback)``: guided PPO top to bottom (setup or resume, then per update
1. the rollout, 2. advantages and returns, 3. the minibatch updates; evaluations and
checkpoints in between)."""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path

import torch

from services.learner.feedback import HFPolicy
from services.learner.ppo.advantages import advantages_and_returns
from services.learner.ppo.config import PPOConfig
from services.learner.ppo.result import Callback, TrainResult
from services.learner.ppo.rollout import collect_rollout
from services.learner.ppo.run import PPORun
from services.learner.ppo.self_imitation import self_imitation_update
from services.learner.ppo.update import update_policy


def train(
    config: PPOConfig,
    callback: Callback | None = None,
    *,
    hf_policy: HFPolicy | None = None,
    checkpoint_path: str | Path | None = None,
    checkpoint_every: int = 10,
) -> TrainResult:
    """Train pi_RL with PPO, guided by ``hf_policy`` if given.

    Parameters
    ----------
    config : PPOConfig
        Hyperparameters, task and seed.
    callback : Callback, optional
        Progress hooks; any hook returning False stops training after that point.
    hf_policy : HFPolicy, optional
        pi_HF for guided exploration (greedy, or sampled with ``hf_guide_sampling``); None
        gives plain PPO.
    checkpoint_path : path, optional
        Where to write a checkpoint every ``checkpoint_every`` updates (and at the end).
        If the file exists, training resumes from it.
    checkpoint_every : int
        Updates between checkpoints.

    Returns
    -------
    TrainResult
    """
    with ExitStack() as stack:
        # ---- setup or resume: networks, optimiser, random streams; evaluation at step 0 ----
        run = PPORun(
            config, stack, callback=callback, hf_policy=hf_policy,
            checkpoint_path=checkpoint_path, checkpoint_every=checkpoint_every,
        )  # fmt: skip
        agent, optimizer, rollout, state = run.agent, run.optimizer, run.rollout, run.state
        while run.running:
            # ---- 1. collect n_steps with the behaviour policy (pi_HF or pi_RL per episode) --
            rollout_start = time.perf_counter()
            run.obs, hooks_go_on, episode_returns, successes = collect_rollout(
                run.env, agent, run.obs, rollout, state, config=config, hf_policy=run.hf_policy,
                rng=run.rng, resets=run.resets, on_step=run.callback.on_step,
                evaluate=run.evaluate,
            )  # fmt: skip
            run.keep_going &= hooks_go_on
            rollout_seconds = time.perf_counter() - rollout_start

            # ---- 2. advantages: GAE (authors) or trace-cut GAE + rho weights (truncated_is) -
            with torch.inference_mode():
                _, next_value = agent(torch.as_tensor(run.obs))
            advantages, returns, weights = advantages_and_returns(
                rollout, float(next_value), config
            )

            # ---- 3. n_epochs of minibatch updates --------------------------------------------
            update_start = time.perf_counter()
            eps_hf = run.eps_hf()
            prior, hf_prior_weight = run.prior(eps_hf)  # pi_HF as a prior (hf_prior_coef)
            metrics = update_policy(
                agent, optimizer, rollout, advantages, returns, weights,
                config=config, rng=run.rng, n_updates_done=state.n_updates,
                prior=prior, prior_weight=hf_prior_weight,
            )  # fmt: skip
            if run.success_replay is not None:  # self-imitation of the successful episodes
                run.remember_successes(successes)
                metrics.update(
                    self_imitation_update(agent, optimizer, run.success_replay, config, run.rng)
                )
            run.end_update(
                metrics, returns=returns, episode_returns=episode_returns, eps_hf=eps_hf,
                rollout_start=rollout_start, rollout_seconds=rollout_seconds,
                update_start=update_start,
            )  # fmt: skip
        if run.final_evaluation_due:  # the trained policy's SPL, not the one before it
            run.evaluate()
        return run.finish()
