"""Step 2 of a PPO update: advantages and value targets of a rollout.

With ``hf_treatment="authors"`` this is plain GAE; with ``"truncated_is"`` the traces are cut
by ``c_t = min(1, pi_old/mu)`` (Retrace) and the value target of each step is
``V + rho_t * A_t`` with ``rho_t = min(is_clip, pi_old/mu)`` (V-trace), ``rho_t`` also
weighting the step's surrogate in the update.
"""

from __future__ import annotations

import numpy as np

from services.learner.ppo.config import PPOConfig
from services.learner.ppo.rollout import Rollout


def compute_advantages(
    rewards: np.ndarray,
    values: np.ndarray,
    episode_ends: np.ndarray,
    next_value: float,
    gamma: float,
    gae_lambda: float,
    traces: np.ndarray | None = None,
) -> np.ndarray:
    """GAE(lambda), optionally with per-step trace cutting (Retrace-style).

    Parameters
    ----------
    rewards, values : ndarray of shape (T,)
        Reward after step t and V(s_t).
    episode_ends : ndarray of shape (T,)
        1 where the episode ended after step t (no bootstrap across it).
    next_value : float
        V of the observation after the last step (ignored if that step ended an episode).
    traces : ndarray of shape (T,), optional
        ``c_t = min(1, pi/mu)`` of each step; the recursion into step t+1 is multiplied by
        ``c_{t+1}``. None means on-policy (all ones), i.e. plain GAE.

    Returns
    -------
    ndarray of shape (T,)
        ``A_t = delta_t + gamma * lambda * c_{t+1} * (1 - end_t) * A_{t+1}``.
    """
    n = len(rewards)
    advantages = np.zeros(n, dtype=np.float64)
    last = 0.0
    for t in reversed(range(n)):
        nonterminal = 1.0 - float(episode_ends[t])
        v_next = next_value if t == n - 1 else values[t + 1]
        c_next = 1.0 if traces is None or t == n - 1 else float(traces[t + 1])
        delta = rewards[t] + gamma * v_next * nonterminal - values[t]
        last = delta + gamma * gae_lambda * c_next * nonterminal * last
        advantages[t] = last
    return advantages


def advantages_and_returns(
    rollout: Rollout, next_value: float, config: PPOConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(advantages, value targets, surrogate weights rho) of ``rollout``; ``next_value`` is
    V of the observation after its last step. The weights are None where every step counts
    once (``hf_treatment="authors"``): the update then skips the multiplication."""
    if config.hf_treatment == "truncated_is":
        ratio_to_mu = np.exp(rollout.pi_logp.astype(np.float64) - rollout.mu_logp)
        traces = np.minimum(1.0, ratio_to_mu)
        weights = np.minimum(config.is_clip, ratio_to_mu)
    else:
        traces = weights = None
    advantages = compute_advantages(
        rollout.rewards,
        rollout.values,
        rollout.ends,
        next_value,
        config.gamma,
        config.gae_lambda,
        traces,
    )
    returns = rollout.values + (advantages if weights is None else weights * advantages)
    return advantages, returns, weights
