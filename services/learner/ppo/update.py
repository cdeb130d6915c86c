"""Step 3 of a PPO update: ``n_epochs`` of minibatch steps on the clipped surrogate.

Optional stabilisers (off by default): ``target_kl`` ends the epoch loop early once a
minibatch's approx KL to the rollout policy exceeds it; ``anneal_lr`` anneals the learning
rate linearly to 0 over the run (CleanRL, SB3).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from services.learner.optimizer import FlatAdam
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig
from services.learner.ppo.rollout import Rollout


def ppo_loss(
    agent: ActorCritic,
    obs: torch.Tensor,
    actions: torch.Tensor,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    weights: torch.Tensor | None,
    config: PPOConfig,
    prior: torch.Tensor | None = None,
    prior_weight: float | torch.Tensor = 0.0,
    *,
    with_stats: bool = True,
) -> tuple[torch.Tensor, dict[str, Any]]:
    """Clipped PPO loss of one minibatch (of each run's minibatch, for a batch of runs).

    ``advantages`` are used as given (:func:`update_policy` normalises them per minibatch
    if ``config.norm_adv``). ``weights`` multiplies each step's surrogate (the truncated
    importance weight rho for off-policy HF steps; None means 1, on-policy). ``prior``
    (pi_HF's action distribution per state) adds ``prior_weight`` times its cross-entropy to
    pi_RL (``hf_prior_coef``). Returns the loss
    and CleanRL-named statistics (empty unless ``with_stats``: computing them costs about a
    tenth of an update step).

    Batches of runs (:mod:`~services.learner.ppo.lockstep`): ``agent`` maps observations of
    shape (runs, minibatch, n_obs) to (runs, minibatch, ...) outputs and every argument has
    the leading run dimension; every mean is over the last (minibatch) dimension, so the loss
    is one per run (``prior_weight`` may be one per run) and each statistic a list of one
    float per run.
    """
    logits, value = agent(obs)
    log_probs = torch.log_softmax(logits, dim=-1)
    new_logp = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean(-1)
    log_ratio = new_logp - old_logp
    ratio = log_ratio.exp()
    # max(unclipped, clipped) of CleanRL. The clipped term only wins where the ratio is
    # outside the clip range, where it has no gradient; where the two are equal, max's
    # backward gives each half the gradient, which sums to the unclipped one. So the clipped
    # term can be detached: same values, same gradients, a smaller graph.
    neg_adv = -advantages
    unclipped = neg_adv * ratio
    with torch.no_grad():
        clipped = neg_adv * torch.clamp(ratio, 1 - config.clip_coef, 1 + config.clip_coef)
    surrogate = torch.where(unclipped >= clipped, unclipped, clipped)
    pg_loss = (surrogate if weights is None else weights * surrogate).mean(-1)
    v_loss = 0.5 * ((value - returns) ** 2).mean(-1)
    loss = pg_loss - config.ent_coef * entropy + config.vf_coef * v_loss
    prior_loss = None
    if prior is not None:
        prior_loss = -(prior * log_probs).sum(-1).mean(-1)
        loss = loss + prior_weight * prior_loss
    if not with_stats:
        return loss, {}
    with torch.no_grad():  # tolist: a float, or a list of one per run
        stats = {
            "losses/policy_loss": pg_loss.tolist(),
            "losses/value_loss": v_loss.tolist(),
            "losses/entropy": entropy.tolist(),
            "losses/approx_kl": ((ratio - 1) - log_ratio).mean(-1).tolist(),
            "losses/clipfrac": ((ratio - 1.0).abs() > config.clip_coef).float().mean(-1).tolist(),
        }
        if prior_loss is not None:
            stats["losses/hf_prior_cross_entropy"] = prior_loss.tolist()
    return loss, stats


MinibatchArguments = list[torch.Tensor | None]
"""The arguments of :func:`ppo_loss` after the agent (observations, actions, old log-probs,
advantages, returns, weights, prior), each stacked over an update's minibatches (shape
(n_epochs * n_minibatches, minibatch_size, ...)); weights and prior None where absent."""


def minibatches(
    rollout: Rollout,
    advantages: np.ndarray,
    returns: np.ndarray,
    weights: np.ndarray | None,
    prior: np.ndarray | None,
    *,
    config: PPOConfig,
    rng: np.random.Generator,
) -> MinibatchArguments:
    """Every minibatch of an update's ``config.n_epochs`` passes over ``rollout``, in order
    (one permutation of the rollout per epoch from ``rng``), advantages normalised per
    minibatch if ``config.norm_adv``."""
    # Every epoch's permutation is drawn first (the same draws as one per epoch), then
    # each minibatch is gathered, and its advantages normalised, by one op per rollout.
    order = np.concatenate([rng.permutation(config.n_steps) for _ in range(config.n_epochs)])
    index = torch.from_numpy(order).view(-1, config.minibatch_size)
    mb_adv = torch.from_numpy(advantages.astype(np.float32))[index]
    if config.norm_adv and config.minibatch_size > 1:
        mb_adv = (mb_adv - mb_adv.mean(1, keepdim=True)) / (mb_adv.std(1, keepdim=True) + 1e-8)
    return [
        torch.from_numpy(rollout.obs)[index],
        torch.from_numpy(rollout.actions)[index],
        torch.from_numpy(rollout.pi_logp)[index],
        mb_adv,
        torch.from_numpy(returns.astype(np.float32))[index],
        None if weights is None else torch.from_numpy(weights.astype(np.float32))[index],
        None if prior is None else torch.from_numpy(prior.astype(np.float32))[index],
    ]  # weights None: all 1, the multiplication is skipped


def learning_rate(config: PPOConfig, n_updates_done: int) -> float:
    """The learning rate of the update after ``n_updates_done`` ones: constant, or annealed
    linearly to 0 over the run with ``config.anneal_lr``."""
    if not config.anneal_lr:
        return config.learning_rate
    n_updates_total = -(-config.total_steps // config.n_steps)
    return config.learning_rate * (1.0 - n_updates_done / n_updates_total)


class UpdateStats:
    """An update's loss statistics, summed over the last epoch begun, and its steps done."""

    def __init__(self, config: PPOConfig) -> None:
        self.n_minibatches = config.n_steps // config.minibatch_size  # per epoch
        self.sums: dict[str, float] = {}
        self.n_in_epoch = 0
        self.n_done = 0
        """Minibatch steps taken."""

    def add(self, i: int, stats: dict[str, float]) -> None:
        """The statistics of minibatch ``i`` (counted from the update's first)."""
        if i % self.n_minibatches == 0:
            self.sums, self.n_in_epoch = {}, 0
        for key, val in stats.items():
            self.sums[key] = self.sums.get(key, 0.0) + val
        self.n_in_epoch += 1

    def metrics(self) -> dict[str, float]:
        """The statistics averaged over the last epoch begun and ``losses/update_epochs``,
        the epochs done (fewer where ``target_kl`` stopped them)."""
        metrics = {key: val / max(self.n_in_epoch, 1) for key, val in self.sums.items()}
        metrics["losses/update_epochs"] = self.n_done / self.n_minibatches
        return metrics


def update_policy(
    agent: ActorCritic,
    optimizer: FlatAdam,
    rollout: Rollout,
    advantages: np.ndarray,
    returns: np.ndarray,
    weights: np.ndarray | None,
    *,
    config: PPOConfig,
    rng: np.random.Generator,
    n_updates_done: int,
    prior: np.ndarray | None = None,
    prior_weight: float = 0.0,
) -> dict[str, float]:
    """``config.n_epochs`` passes of minibatch steps over ``rollout``; ``weights`` (rho)
    multiply each step's surrogate, None meaning 1; ``prior`` (pi_HF's action distribution
    at each rollout state) adds ``prior_weight`` times its cross-entropy to pi_RL. The
    learning rate is annealed from ``n_updates_done`` (the updates before this one) if
    ``config.anneal_lr``.

    Returns the loss statistics averaged over the last epoch begun and
    ``losses/update_epochs``, the epochs done (fewer where ``target_kl`` stopped them).
    """
    arguments = minibatches(rollout, advantages, returns, weights, prior, config=config, rng=rng)
    n_total = len(arguments[0])
    rows = zip(*(a if a is not None else [None] * n_total for a in arguments), strict=True)
    optimizer.lr = learning_rate(config, n_updates_done)
    early_stop = config.target_kl is not None  # needs every minibatch's approx KL
    update_stats = UpdateStats(config)
    for i, minibatch in enumerate(rows):
        last_epoch = i >= n_total - update_stats.n_minibatches
        *losses_of, mb_prior = minibatch
        loss, stats = ppo_loss(
            agent, *losses_of, config, mb_prior, prior_weight, with_stats=last_epoch or early_stop
        )
        update_stats.add(i, stats)
        if early_stop and stats["losses/approx_kl"] > config.target_kl:
            break  # this minibatch is already too far from the rollout policy
        optimizer.zero_grad()
        loss.backward()
        optimizer.clip_grad_norm_(config.max_grad_norm)
        optimizer.step()
        update_stats.n_done += 1
    return update_stats.metrics()


def update_metrics(
    global_step: int,
    rollout: Rollout,
    returns: np.ndarray,
    episode_returns: list[float],
    guided: bool,
    learning_rate: float,
    eps_hf: float,
) -> dict[str, float]:
    """CleanRL-named metrics of an update besides the loss statistics (``episode_returns``:
    of the episodes that ended in ``rollout``; ``eps_hf``: eps_HF at the update)."""
    var_returns = float(np.var(returns))
    explained = 1.0 - float(np.var(returns - rollout.values)) / var_returns if var_returns else None
    return {
        "global_step": float(global_step),
        "losses/explained_variance": float("nan") if explained is None else explained,
        "charts/eps_hf": eps_hf,
        "charts/hf_step_fraction": float(np.mean(rollout.is_hf)) if guided else 0.0,
        "charts/episodic_return": (
            float(np.mean(episode_returns)) if episode_returns else float("nan")
        ),
        "charts/learning_rate": learning_rate,
    }
