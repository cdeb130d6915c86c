"""The idealised Bayesian reference for stage 2: how many labels identify the oracle's path.

Issue #24: an idealised learner that knows the path's states and may ask about any (state,
action) at any time (no robot to move, no off-path state, no relabelled prefix) receives
hard labels through a binary symmetric channel of accuracy C and keeps the exact posterior
of the optimal action per state (:class:`services.learner.query.PathPosterior`'s evidence,
summed log-likelihood ratios). The path is *identified* when the MAP action of every path
state is one of the oracle's optimal actions there. Query rules:

* ``round_robin``: state ``t mod S``, action ``(t // S) mod 3`` (uniform allocation);
* ``adaptive``: the least certain state (lowest MAP log-odds), action by top-two Thompson
  sampling (:func:`services.learner.query.top_two_thompson`), flat prior;
* ``adaptive_forward``: the same with the matched "mostly forward" prior (P(forward) the
  share of path states where forward is optimal, the rest split evenly).

:func:`oracle_path` gives the real task's states: the oracle policy's way from the start of
a task's map (services.sim's oracle). Draws are vectorised: many runs cost one loop over
labels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import closing

import gymnasium as gym
import numpy as np
from scipy.special import logsumexp

from services.core.actions import N_ACTIONS, Action

REFERENCE_RULES = ("round_robin", "adaptive", "adaptive_forward")


def oracle_path(task: str = "sssg", seed: int = 0) -> np.ndarray:
    """Optimal-action mask (S, 3) of the states on the oracle policy's path from the task's
    start (reset ``seed``; SSSG has one start). Ties break forward, left, right, as the
    oracle policy's do."""
    from services.learner.specs import TASK_ENV_IDS

    with closing(gym.make(TASK_ENV_IDS[task], reward_mode="sparse")) as env:
        env.reset(seed=seed)
        masks = []
        while True:
            optimal = env.unwrapped.optimal_actions()  # type: ignore[attr-defined]
            masks.append([a in optimal for a in range(N_ACTIONS)])
            _, _, terminated, truncated, info = env.step(min(optimal))
            if terminated or truncated:
                if not info.get("is_success", False):
                    raise RuntimeError(f"the oracle policy did not reach the goal of {task}")
                return np.array(masks, dtype=bool)


def toy_path(n_states: int = 19, n_turns: int = 3, seed: int = 0) -> np.ndarray:
    """A toy path: ``n_states`` states, one optimal action each, forward except at
    ``n_turns`` states (turns left or right at random)."""
    rng = np.random.default_rng(seed)
    optimal = np.full(n_states, int(Action.FORWARD))
    turns = rng.choice(n_states, n_turns, replace=False)
    optimal[turns] = rng.choice([int(Action.TURN_LEFT), int(Action.TURN_RIGHT)], n_turns)
    return np.eye(N_ACTIONS, dtype=bool)[optimal]


def matched_forward_prior(mask: np.ndarray) -> np.ndarray:
    """Log prior: P(forward) = share of states where forward is optimal, others split."""
    forward = float(np.clip(mask[:, int(Action.FORWARD)].mean(), 1e-3, 1 - 1e-3))
    prior = np.full(N_ACTIONS, (1.0 - forward) / (N_ACTIONS - 1))
    prior[int(Action.FORWARD)] = forward
    return np.log(prior)


def identified_fraction(
    mask: np.ndarray,
    accuracy: float,
    budgets: Sequence[int],
    rule: str,
    draws: int = 1000,
    seed: int = 0,
) -> dict[int, float]:
    """Fraction of ``draws`` runs whose MAP path is all optimal after each budget.

    Parameters
    ----------
    mask : numpy.ndarray
        (S, 3) optimal actions per path state (:func:`oracle_path`, :func:`toy_path`).
    accuracy : float
        C of the binary symmetric label channel (> 0.5).
    budgets : sequence of int
        Label counts at which to measure.
    rule : str
        One of :data:`REFERENCE_RULES`.
    """
    if rule not in REFERENCE_RULES:
        raise ValueError(f"unknown rule {rule!r}; expected one of {REFERENCE_RULES}")
    if not 0.5 < accuracy < 1.0:
        raise ValueError(f"accuracy must be in (0.5, 1), got {accuracy}")
    budgets = sorted(set(int(b) for b in budgets))
    n_states = len(mask)
    rng = np.random.default_rng(seed)
    step = math.log(accuracy / (1.0 - accuracy))
    log_prior = (
        matched_forward_prior(mask)
        if rule == "adaptive_forward"
        else np.full(N_ACTIONS, -math.log(N_ACTIONS))
    )
    evidence = np.zeros((draws, n_states, N_ACTIONS))
    runs = np.arange(draws)
    out: dict[int, float] = {}
    for t in range(1, budgets[-1] + 1):
        if rule == "round_robin":
            state = np.full(draws, (t - 1) % n_states)
            action = np.full(draws, ((t - 1) // n_states) % N_ACTIONS)
        else:
            log_q = log_prior + evidence
            log_q -= logsumexp(log_q, axis=2, keepdims=True)
            leader = np.argmax(log_q, axis=2)[..., None]
            best = np.take_along_axis(log_q, leader, axis=2)[..., 0]
            others = np.where(np.arange(N_ACTIONS) == leader, -np.inf, log_q)
            state = np.argmin(best - logsumexp(others, axis=2), axis=1)  # least certain
            action = _top_two(np.exp(log_q[runs, state]), rng)
        correct = mask[state, action]
        says_correct = np.where(rng.random(draws) < accuracy, correct, ~correct)
        evidence[runs, state, action] += np.where(says_correct, step, -step)
        if t in budgets:
            chosen = np.argmax(log_prior + evidence, axis=2)
            on_path = mask[np.arange(n_states)[None, :], chosen]
            out[t] = float(on_path.all(axis=1).mean())
    return out


def _top_two(q: np.ndarray, rng: np.random.Generator, beta: float = 0.5) -> np.ndarray:
    """Top-two Thompson sampling per row of ``q`` (draws, actions)."""
    cumulative = np.cumsum(q, axis=1)
    k1 = (rng.random((len(q), 1)) > cumulative).sum(axis=1).clip(max=N_ACTIONS - 1)
    rest = q.copy()
    rest[np.arange(len(q)), k1] = 0.0
    total = rest.sum(axis=1, keepdims=True)
    rest = np.where(total > 0, rest / np.where(total > 0, total, 1.0), q)
    k2 = (rng.random((len(q), 1)) > np.cumsum(rest, axis=1)).sum(axis=1).clip(max=N_ACTIONS - 1)
    return np.where(rng.random(len(q)) < beta, k1, k2)


def binary_entropy(p: float) -> float:
    """H(p) in bits."""
    if p in (0.0, 1.0):
        return 0.0
    return -(p * math.log2(p) + (1 - p) * math.log2(1 - p))


def path_bits(mask: np.ndarray) -> float:
    """Bits that single out one optimal action per path state under a uniform prior:
    ``sum_s log2(3 / |optimal(s)|)`` (19 log2 3 = 30.1 for 19 states with one each)."""
    return float(np.sum(np.log2(N_ACTIONS / mask.sum(axis=1))))


def information_bound(bits: float, accuracy: float, gain: float = 1.0) -> float:
    """Labels that carry ``bits`` through a binary symmetric channel of accuracy C:
    ``bits / (gain (1 - H(C)))`` (``gain``: a channel's bits per label over the hard
    label's, e.g. the soft channel's measured 1.52 at C = 0.6)."""
    return bits / (gain * (1.0 - binary_entropy(accuracy)))
