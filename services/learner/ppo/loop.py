"""``train(config, callback)``: guided PPO top to bottom (setup or resume, then per update
1. the rollout, 2. advantages and returns, 3. the minibatch updates; evaluations and
checkpoints in between)."""

from __future__ import annotations

import time
from contextlib import closing
from dataclasses import asdict
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

from services.learner.checkpoint import Checkpoint, RunState, load_checkpoint, save_checkpoint
from services.learner.evaluation import evaluate_spl
from services.learner.feedback import HFPolicy
from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo.advantages import advantages_and_returns
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig, episode_epsilon, prior_weight
from services.learner.ppo.rollout import Rollout, begin_episode, collect_rollout
from services.learner.ppo.self_imitation import (
    SuccessReplay,
    replay_episode,
    self_imitation_update,
)
from services.learner.ppo.update import update_metrics, update_policy
from services.learner.seeding import RunSeeds, Stream
from services.learner.training import Callback, TrainResult


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
    start_time = time.perf_counter()
    callback = callback or Callback()
    guided = hf_policy is not None
    with (
        closing(gym.make(config.env_id, **config.env_kwargs)) as env,
        closing(gym.make(config.env_id, **config.env_kwargs)) as eval_env,
    ):
        # ---- setup: networks, optimiser and the run's random streams ------------------------
        n_actions = int(env.action_space.n)
        if config.explore_coef > 0 and not hasattr(env.unwrapped, "observation_cell"):
            raise ValueError(
                f"explore_coef needs an env with observation_cell(obs, size_m) (BrainNav "
                f"envs have it); {config.env_id} has none"
            )
        seeds = RunSeeds(config.seed)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seeds.int_seed(Stream.TORCH_INIT))
            agent = ActorCritic(
                ObsNormalizer.from_space(env.observation_space), n_actions, config.hidden_sizes
            )
        optimizer = FlatAdam(agent.parameters(), lr=config.learning_rate, eps=config.adam_eps)
        rng = seeds.generator(Stream.ACTIONS)
        resets = seeds.training_resets()
        state = RunState()
        checkpoint = Path(checkpoint_path) if checkpoint_path is not None else None

        best_agent: dict[str, torch.Tensor] | None = None  # weights at state.best_step
        success_replay = (
            SuccessReplay(env.observation_space.shape[0], config.sil_capacity)
            if config.sil_coef > 0
            else None
        )

        def save() -> None:
            assert checkpoint is not None
            snapshot = (asdict(config), agent, optimizer, rng, resets, state, hf_policy)
            save_checkpoint(
                checkpoint,
                Checkpoint.capture(
                    *snapshot,
                    best_agent=best_agent,
                    success_replay=None if success_replay is None else success_replay.state_dict(),
                ),
            )

        if checkpoint is not None and checkpoint.exists():
            restored = load_checkpoint(checkpoint, asdict(config), asdict(PPOConfig()))
            state = restored.restore(agent, optimizer, rng, resets, hf_policy)
            best_agent = restored.best_agent
            if success_replay is not None and restored.success_replay is not None:
                success_replay.load_state_dict(restored.success_replay)
            obs, _ = env.reset(seed=state.episode_seed)
            for action in state.episode_actions:  # replay the episode in progress
                obs, *_ = env.step(action)
        else:
            obs = begin_episode(env, state, resets, rng, config, guided)

        def greedy(o: np.ndarray) -> int:
            with torch.inference_mode():
                logits, _ = agent(torch.as_tensor(o))
            return int(torch.argmax(logits))

        def evaluate() -> bool:
            nonlocal best_agent
            spl = evaluate_spl(eval_env, greedy, config.eval_seeds)
            state.curve.append((state.global_step, spl))
            if state.best_spl is None or spl > state.best_spl:  # the first of equal bests
                state.best_step, state.best_spl = state.global_step, spl
                best_agent = {k: v.detach().clone() for k, v in agent.state_dict().items()}
            return callback.on_eval(state.global_step, spl)

        keep_going = evaluate() if not state.curve else True
        rollout = Rollout.empty(config.n_steps, env.observation_space.shape[0])

        while keep_going and state.global_step < config.total_steps:
            # ---- 1. collect n_steps with the behaviour policy (pi_HF or pi_RL per episode) --
            rollout_start = time.perf_counter()
            obs, hooks_go_on, episode_returns, successes = collect_rollout(
                env, agent, obs, rollout, state, config=config, hf_policy=hf_policy, rng=rng,
                resets=resets, on_step=callback.on_step, evaluate=evaluate,
            )  # fmt: skip
            keep_going &= hooks_go_on
            rollout_seconds = time.perf_counter() - rollout_start

            # ---- 2. advantages: GAE (authors) or trace-cut GAE + rho weights (truncated_is) -
            with torch.inference_mode():
                _, next_value = agent(torch.as_tensor(obs))
            advantages, returns, weights = advantages_and_returns(
                rollout, float(next_value), config
            )

            # ---- 3. n_epochs of minibatch updates --------------------------------------------
            update_start = time.perf_counter()
            eps_hf = episode_epsilon(state.global_step, state.episodes, config) if guided else 0.0
            hf_prior_weight = prior_weight(eps_hf, config)
            prior = (  # pi_HF as a prior on pi_RL (hf_prior_coef), while guidance lasts
                hf_policy.sampling_probs(rollout.obs)
                if hf_policy is not None and hf_prior_weight > 0.0
                else None
            )
            metrics = update_policy(
                agent, optimizer, rollout, advantages, returns, weights,
                config=config, rng=rng, n_updates_done=state.n_updates,
                prior=prior, prior_weight=hf_prior_weight,
            )  # fmt: skip
            if success_replay is not None:  # self-imitation of the successful episodes
                for seed, actions in successes:
                    observations, rewards = replay_episode(
                        eval_env, seed, actions, config.reward_scale
                    )
                    success_replay.add_episode(
                        observations, np.asarray(actions), rewards, config.gamma
                    )
                metrics.update(self_imitation_update(agent, optimizer, success_replay, config, rng))
            state.n_updates += 1
            metrics.update(
                update_metrics(
                    state.global_step, rollout, returns, episode_returns, guided, optimizer.lr,
                    eps_hf,
                )
            )  # fmt: skip
            if config.explore_coef > 0:
                metrics["charts/explored_cells"] = float(len(state.visits))
            metrics["charts/SPS"] = config.n_steps / max(time.perf_counter() - rollout_start, 1e-9)
            metrics["charts/rollout_seconds"] = rollout_seconds
            metrics["charts/update_seconds"] = time.perf_counter() - update_start
            state.metrics.append(metrics)
            keep_going &= callback.on_update(state.global_step, metrics)
            if checkpoint is not None and (
                state.n_updates % checkpoint_every == 0 or not keep_going
            ):
                save()

        if checkpoint is not None:
            save()
    return TrainResult(
        config=config,
        agent=agent,
        curve=list(state.curve),
        metrics=state.metrics,
        global_step=state.global_step,
        n_episodes=state.n_episodes,
        n_hf_episodes=state.n_hf_episodes,
        episodes=[tuple(e) for e in state.episodes],
        stopped_early=state.global_step < config.total_steps,
        wall_seconds=time.perf_counter() - start_time,
        best_step=state.best_step,
        best_agent=best_agent,
    )
