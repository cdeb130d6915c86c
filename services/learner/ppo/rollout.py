"""Step 1 of a PPO update: ``n_steps`` in the env with the behaviour policy.

Each episode follows pi_HF with probability ``eps_HF`` (drawn at its start), else pi_RL. The
rollout stores pi_RL's log-prob of every action taken and the behaviour policy's (``mu``):
the two are equal on RL steps; a greedy pi_HF step has ``mu = 1``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from services.learner.checkpoint import RunState
from services.learner.feedback import HFPolicy
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig, episode_epsilon
from services.learner.seeding import TrainingResets


@dataclass
class Rollout:
    """The storage of one rollout of ``n_steps`` (CleanRL's buffers), reused every update."""

    obs: np.ndarray
    actions: np.ndarray
    pi_logp: np.ndarray
    """log pi_RL(a_t|s_t) of the policy that collected the rollout."""
    mu_logp: np.ndarray
    """log mu(a_t|s_t) of the behaviour policy (0 for greedy pi_HF steps, pi_logp for RL)."""
    is_hf: np.ndarray
    rewards: np.ndarray
    """Scaled reward, plus gamma * V(s_T) where a time limit cut the episode."""
    values: np.ndarray
    ends: np.ndarray

    @classmethod
    def empty(cls, n_steps: int, n_obs: int) -> Rollout:
        """Zeroed buffers."""
        return cls(
            obs=np.zeros((n_steps, n_obs), dtype=np.float32),
            actions=np.zeros(n_steps, dtype=np.int64),
            pi_logp=np.zeros(n_steps, dtype=np.float32),
            mu_logp=np.zeros(n_steps, dtype=np.float32),
            is_hf=np.zeros(n_steps, dtype=bool),
            rewards=np.zeros(n_steps, dtype=np.float64),
            values=np.zeros(n_steps, dtype=np.float64),
            ends=np.zeros(n_steps, dtype=np.float64),
        )


def sample_categorical(probs: np.ndarray, rng: np.random.Generator) -> int:
    """Inverse-CDF draw from a categorical distribution (float64 probabilities)."""
    cdf = np.cumsum(probs)
    return int(min(np.searchsorted(cdf, rng.random() * cdf[-1]), len(cdf) - 1))


def begin_episode(
    env: gym.Env,
    state: RunState,
    resets: TrainingResets,
    rng: np.random.Generator,
    config: PPOConfig,
    guided: bool,
) -> np.ndarray:
    """Reset ``env`` with the next training reset seed and draw whether the new episode
    follows pi_HF (with probability eps_HF; never if not ``guided`` or once guidance is
    withdrawn); its first observation."""
    state.episode_seed = resets.next()
    state.episode_actions = []
    state.episode_return = 0.0
    state.episode_handed_over = False
    state.episode_seen = set()
    obs, _ = env.reset(seed=state.episode_seed)
    eps_hf = episode_epsilon(state.global_step, state.episodes, config)
    state.episode_is_hf = guided and rng.random() < eps_hf
    return obs


@dataclass
class StepOutcome:
    """What one step of :func:`rollout_step` reports besides the state it advanced."""

    obs: np.ndarray
    """The observation to act on next (the new episode's first after an end)."""
    info: dict[str, Any]
    episode_return: float | None = None
    """The (scaled) return of the episode this step ended, None if it goes on."""
    success: tuple[int, list[int]] | None = None
    """(reset seed, actions) of the episode this step ended at the goal."""


def rollout_step(
    env: gym.Env,
    obs: np.ndarray,
    t: int,
    log_probs: np.ndarray,
    value: float,
    rollout: Rollout,
    state: RunState,
    *,
    config: PPOConfig,
    hf_policy: HFPolicy | None,
    rng: np.random.Generator,
    resets: TrainingResets,
    value_of: Callable[[np.ndarray], float],
) -> StepOutcome:
    """Step ``t`` of a rollout from ``obs``, where pi_RL's log-probs are ``log_probs`` and
    its value ``value``: choose the behaviour policy's action, step ``env``, store the step
    in ``rollout`` and advance ``state`` (a new episode begins after an end). ``value_of``
    gives V of an observation (the bootstrap of a time-limit cut)."""
    follows_hf = state.episode_is_hf and not state.episode_handed_over
    if follows_hf and config.hf_handover_on_revisit:
        seen = np.asarray(obs, dtype=np.float32).tobytes()
        if seen in state.episode_seen:  # pi_HF is in a loop: pi_RL takes over
            state.episode_handed_over, follows_hf = True, False
        else:
            state.episode_seen.add(seen)
    if not follows_hf:
        action = sample_categorical(np.exp(log_probs.astype(np.float64)), rng)
        mu_logp = float(log_probs[action])
    elif config.hf_guide_sampling:
        hf_probs = hf_policy.sampling_probs(obs).astype(np.float64)
        action = sample_categorical(hf_probs, rng)
        mu_logp = float(np.log(hf_probs[action]))
    else:
        action = hf_policy.act(obs)  # greedy pi_HF: mu(a|s) = 1
        mu_logp = 0.0
    next_obs, reward, terminated, truncated, info = env.step(action)
    reward = float(reward) * config.reward_scale
    bonus = 0.0
    if config.explore_coef > 0 and not terminated:
        cell = env.unwrapped.observation_cell(next_obs, config.explore_cell_m)
        state.visits[cell] = visits = state.visits.get(cell, 0) + 1
        bonus = config.explore_coef * config.reward_scale / math.sqrt(visits)
    if truncated and not terminated:  # time limit: bootstrap the cut-off tail
        reward += config.gamma * value_of(next_obs)
    rollout.obs[t] = obs
    rollout.actions[t] = action
    rollout.pi_logp[t] = log_probs[action]
    rollout.mu_logp[t] = mu_logp
    rollout.is_hf[t] = follows_hf
    rollout.rewards[t] = reward + bonus
    rollout.values[t] = value
    rollout.ends[t] = float(terminated or truncated)
    state.global_step += 1
    state.episode_actions.append(action)
    state.episode_return += float(reward)
    if not (terminated or truncated):
        return StepOutcome(next_obs, info)
    outcome = StepOutcome(next_obs, info, episode_return=state.episode_return)
    if info.get("is_success", False):
        outcome.success = (state.episode_seed, list(state.episode_actions))
    state.episodes.append(
        (
            state.global_step,
            len(state.episode_actions),
            bool(info.get("is_success", False)),
            bool(info.get("collision", False)),
            state.episode_is_hf,
        )
    )
    state.n_episodes += 1
    state.n_hf_episodes += int(state.episode_is_hf)
    outcome.obs = begin_episode(env, state, resets, rng, config, hf_policy is not None)
    return outcome


def collect_rollout(
    env: gym.Env,
    agent: ActorCritic,
    obs: np.ndarray,
    rollout: Rollout,
    state: RunState,
    *,
    config: PPOConfig,
    hf_policy: HFPolicy | None,
    rng: np.random.Generator,
    resets: TrainingResets,
    on_step: Callable[[int, dict[str, Any]], bool],
    evaluate: Callable[[], bool],
) -> tuple[np.ndarray, bool, list[float], list[tuple[int, list[int]]]]:
    """Fill ``rollout`` with ``config.n_steps`` env steps from ``obs``, advancing ``state``
    (step and episode counters, the episode in progress). ``on_step`` runs after every step,
    ``evaluate`` every ``config.eval_every`` steps.

    Returns the observation after the last step, whether every hook asked to go on, the
    (scaled) returns of the episodes that ended, and the (reset seed, actions) of those that
    reached the goal.
    """
    keep_going = True
    episode_returns: list[float] = []
    successes: list[tuple[int, list[int]]] = []
    for t in range(config.n_steps):
        with torch.inference_mode():
            logits, value = agent(torch.as_tensor(obs))
            log_probs = torch.log_softmax(logits, dim=-1).numpy()
        step = rollout_step(
            env, obs, t, log_probs, float(value), rollout, state, config=config,
            hf_policy=hf_policy, rng=rng, resets=resets, value_of=agent.value_of,
        )  # fmt: skip
        obs = step.obs
        if step.episode_return is not None:
            episode_returns.append(step.episode_return)
        if step.success is not None:
            successes.append(step.success)
        keep_going &= on_step(state.global_step, step.info)
        if state.global_step % config.eval_every == 0:
            keep_going &= evaluate()
    return obs, keep_going, episode_returns, successes
