"""Stage 3 of Brain-Guided RL: PPO from sparse reward, with pi_HF guiding exploration.

Akinola et al., ICRA 2020, §Efficient Sparse-Reward RL with Guided Exploration and
Algorithm 1 (``Train the RL policy``). Written top to bottom in the style of CleanRL's
``ppo.py`` (one env, explicit GAE, clipped surrogate), but exposed as
``train(config, callback) -> TrainResult``.

Guided exploration. At the start of every episode the behaviour policy is the greedy pi_HF
with probability ``eps_HF(t)``, else pi_RL. ``eps_HF`` is 1 during an optional HF-only
warm-up of ``hf_warmup_steps``, then falls linearly from ``hf_eps_init`` (0.8) to 0 at
``hf_t_trans_fraction`` (50 %) of ``total_steps``. Without an HF policy this is plain PPO, so
RL-sparse, RL-rich and HF+sparse share the network, the hyperparameters and this code.

Two treatments of the steps that pi_HF chose (``hf_treatment``):

* ``"authors"`` - what the authors' code does: the step is stored with pi_RL's log-prob of
  the HF action and used as if pi_RL had sampled it (no importance correction). This is
  biased: the surrogate pushes up pi_RL(a_HF|s) in proportion to the advantage, i.e. it acts
  like advantage-weighted imitation of pi_HF.
* ``"truncated_is"`` - off-policy-correct: the behaviour policy mu is stored per step
  (mu(a_HF|s) = 1 for the greedy pi_HF, mu = pi_RL for RL steps). Advantages use traces cut
  by ``c_t = min(1, pi_old/mu)`` (Retrace, Munos et al. 2016), the surrogate of each step is
  weighted by ``rho_t = min(is_clip, pi_old/mu)`` and the value target is
  ``V + rho_t * A_t`` (V-trace, Espeholt et al. 2018); the PPO clip is taken against the
  policy that collected the batch (decoupled PPO, Hilton et al. 2022). On RL steps
  ``pi_old/mu = 1`` and everything reduces to standard PPO.

Reward scale. Rewards are multiplied by ``reward_scale`` before GAE, identically for every
method (0.01 by default: +-100 terminal rewards become +-1; a 2-D
mock-up only learned with 1/100). Time-limit truncation is bootstrapped with
``gamma * V(s_T)``.

Stabilisers (off by default, so the paper's setting is unchanged): ``target_kl`` ends an
update's epoch loop early once a minibatch's approx KL to the rollout policy exceeds it, and
``anneal_lr`` anneals the learning rate linearly to 0 over the run (CleanRL, SB3).

Best checkpoint. Like SB3's ``EvalCallback``, training keeps the weights of the best
evaluation (the first of equal bests) beside the last: ``TrainResult.best_agent`` and
``best_step``; both are in the checkpoint, so a resumed run keeps them too.

Determinism and resume. All randomness comes from ``config.seed`` through one
``numpy.random.SeedSequence`` (:mod:`services.learner.seeding`): torch init (under a forked
RNG), a numpy Generator for sampling and minibatches, and the training reset seeds are
separate child streams, disjoint from the evaluation starts. Checkpoints
(:mod:`services.learner.checkpoint`) are written at update boundaries; a resumed run ends
exactly as an uninterrupted one.

Speed. The actor and critic are evaluated together (:class:`~services.learner.networks.TwinMLP`)
and optimised by :class:`~services.learner.optimizer.FlatAdam` (clip + Adam on one flat
buffer); the tests check both against a plain ``nn.Linear`` / ``torch.optim.Adam`` /
``Categorical`` PPO to a tolerance.

Reading order: :class:`PPOConfig`, :func:`hf_epsilon`, :class:`ActorCritic`,
:func:`compute_advantages`, :func:`ppo_loss`, then :func:`train` (1. rollout with the
behaviour policy, 2. advantages and returns, 3. minibatch updates).
"""

from __future__ import annotations

import time
from contextlib import closing
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from services.learner.checkpoint import Checkpoint, RunState, load_checkpoint, save_checkpoint
from services.learner.evaluation import evaluate_spl
from services.learner.feedback import HFPolicy
from services.learner.networks import ObsNormalizer, TwinMLP
from services.learner.optimizer import FlatAdam
from services.learner.seeding import RunSeeds, Stream, evaluation_reset_seeds
from services.learner.training import Callback, TrainResult

HFTreatment = Literal["authors", "truncated_is"]


@dataclass
class PPOConfig:
    """Hyperparameters of (guided) PPO; defaults follow the authors' public code."""

    env_id: str = "services.sim:BrainNav-SSSG-v0"
    """Gymnasium id of the task (its TimeLimit applies)."""
    env_kwargs: dict[str, Any] = field(default_factory=lambda: {"reward_mode": "sparse"})
    """Keyword arguments of ``gymnasium.make`` (reward_mode, map_path, ...)."""
    seed: int = 0
    """Seed of the run: the entropy of the ``SeedSequence`` whose children seed the network
    init, sampling, minibatches and training resets (``services.learner.seeding``)."""
    total_steps: int = 40_000
    """Environment steps of training (the paper's budget)."""
    n_steps: int = 128
    """Rollout length per update (one env)."""
    n_epochs: int = 64
    """Passes over each rollout (a very high replay ratio, as the authors)."""
    minibatch_size: int = 64
    """Minibatch size of the PPO update."""
    learning_rate: float = 3e-4
    """Adam learning rate (the initial one with ``anneal_lr``)."""
    anneal_lr: bool = False
    """Anneal the learning rate linearly to 0 over the updates of the run (CleanRL's
    ``anneal_lr``); off by default, as the authors' constant rate."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    gamma: float = 0.99
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clip_coef: float = 0.2
    """PPO ratio clip."""
    ent_coef: float = 0.02
    """Entropy bonus coefficient."""
    vf_coef: float = 0.5
    """Value loss coefficient."""
    max_grad_norm: float = 25.0
    """Global gradient-norm clip."""
    target_kl: float | None = None
    """Early stop of an update: the remaining minibatch steps of the ``n_epochs`` are skipped
    once a minibatch's approx KL to the rollout policy exceeds this (checked before its
    step, as SB3 does, without SB3's factor 1.5). None (default): all epochs, as the
    authors."""
    norm_adv: bool = True
    """Normalise advantages per minibatch (CleanRL default)."""
    reward_scale: float = 0.01
    """Multiplier of every reward before learning; identical for all methods."""
    hidden_sizes: tuple[int, ...] = (64, 64)
    """Hidden layers of the (separate) actor and critic MLPs, tanh activations."""
    eval_every: int = 2000
    """Evaluate the greedy pi_RL every this many env steps (and at step 0)."""
    eval_seeds: tuple[int, ...] = evaluation_reset_seeds(1)
    """Reset seeds of the fixed evaluation starts (see ``evaluation.eval_seeds``)."""
    hf_eps_init: float = 0.8
    """eps_HF at the end of the warm-up: probability that an episode follows pi_HF."""
    hf_t_trans_fraction: float = 0.5
    """eps_HF reaches 0 at this fraction of ``total_steps``."""
    hf_warmup_steps: int = 0
    """Initial steps during which every episode follows pi_HF."""
    hf_treatment: HFTreatment = "authors"
    """How PPO uses the steps pi_HF chose: ``authors`` or ``truncated_is`` (module doc)."""
    is_clip: float = 1.0
    """rho-bar, the truncation of the importance weight of the surrogate (truncated_is)."""
    hf_guide_sampling: bool = False
    """HF episodes sample from pi_HF's softened distribution instead of its argmax (the
    paper's greedy pi_HF is the default; a factor studied in docs/reproduction.md)."""

    def __post_init__(self) -> None:
        self.hidden_sizes = tuple(self.hidden_sizes)
        self.eval_seeds = tuple(self.eval_seeds)
        if self.n_steps % self.minibatch_size != 0:
            raise ValueError(
                f"n_steps ({self.n_steps}) must be a multiple of minibatch_size "
                f"({self.minibatch_size})"
            )
        if self.total_steps < self.n_steps:
            raise ValueError("total_steps must be at least n_steps")
        if self.hf_treatment not in ("authors", "truncated_is"):
            raise ValueError(
                f"hf_treatment must be 'authors' or 'truncated_is', not {self.hf_treatment!r}"
            )
        if not 0.0 <= self.hf_eps_init <= 1.0:
            raise ValueError(f"hf_eps_init must be in [0, 1], got {self.hf_eps_init}")
        if not 0.0 < self.hf_t_trans_fraction <= 1.0:
            raise ValueError("hf_t_trans_fraction must be in (0, 1]")
        if self.eval_every < 1 or not self.eval_seeds:
            raise ValueError("eval_every must be >= 1 and eval_seeds non-empty")
        if self.target_kl is not None and not self.target_kl > 0.0:
            raise ValueError(f"target_kl must be > 0 or None, got {self.target_kl}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PPOConfig:
        """Rebuild from ``asdict`` output (e.g. JSON)."""
        return cls(**data)


def hf_epsilon(global_step: int, config: PPOConfig) -> float:
    """eps_HF at a step: 1 in the warm-up, then linear from eps_init to 0 at t_trans."""
    if global_step < config.hf_warmup_steps:
        return 1.0
    t_trans = config.hf_t_trans_fraction * config.total_steps
    span = t_trans - config.hf_warmup_steps
    if span <= 0:
        return 0.0
    progress = (global_step - config.hf_warmup_steps) / span
    return max(0.0, config.hf_eps_init * (1.0 - progress))


class ActorCritic(nn.Module):
    """Fixed observation normalisation, then separate actor and critic tanh MLPs.

    The two towers share nothing but are evaluated together (:class:`TwinMLP`).
    """

    def __init__(
        self, normalizer: ObsNormalizer, n_actions: int, hidden_sizes: tuple[int, ...]
    ) -> None:
        super().__init__()
        self.normalizer = normalizer
        self.towers = TwinMLP(normalizer.n_obs, hidden_sizes, n_actions)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(action logits, state value) for one observation or a batch."""
        # .forward: nn.Module's call machinery costs ~1 us a submodule on this hot path
        if obs.dim() == 1:
            out = self.towers.forward(self.normalizer.forward(obs.unsqueeze(0)))
            return out[0, 0], out[1, 0, 0]
        out = self.towers.forward(self.normalizer.forward(obs))
        return out[0], out[1, :, 0]


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


def ppo_loss(
    agent: ActorCritic,
    obs: torch.Tensor,
    actions: torch.Tensor,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    weights: torch.Tensor | None,
    config: PPOConfig,
    *,
    with_stats: bool = True,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Clipped PPO loss of one minibatch.

    ``advantages`` are used as given (``train`` normalises them per minibatch if
    ``config.norm_adv``). ``weights`` multiplies each step's surrogate (the truncated
    importance weight rho for off-policy HF steps; None means 1, on-policy). Returns the loss
    and CleanRL-named statistics (empty unless ``with_stats``: computing them costs about a
    tenth of an update step).
    """
    logits, value = agent(obs)
    log_probs = torch.log_softmax(logits, dim=-1)
    new_logp = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    entropy = -(log_probs.exp() * log_probs).sum(-1).mean()
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
    pg_loss = (surrogate if weights is None else weights * surrogate).mean()
    v_loss = 0.5 * ((value - returns) ** 2).mean()
    loss = pg_loss - config.ent_coef * entropy + config.vf_coef * v_loss
    if not with_stats:
        return loss, {}
    with torch.no_grad():
        stats = {
            "losses/policy_loss": float(pg_loss),
            "losses/value_loss": float(v_loss),
            "losses/entropy": float(entropy),
            "losses/approx_kl": float(((ratio - 1) - log_ratio).mean()),
            "losses/clipfrac": float(((ratio - 1.0).abs() > config.clip_coef).float().mean()),
        }
    return loss, stats


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


def _sample(probs: np.ndarray, rng: np.random.Generator) -> int:
    """Inverse-CDF draw from a categorical distribution (float64 probabilities)."""
    cdf = np.cumsum(probs)
    return int(min(np.searchsorted(cdf, rng.random() * cdf[-1]), len(cdf) - 1))


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
    with (
        closing(gym.make(config.env_id, **config.env_kwargs)) as env,
        closing(gym.make(config.env_id, **config.env_kwargs)) as eval_env,
    ):
        # ---- setup: networks, optimiser and the run's random streams ------------------------
        n_actions = int(env.action_space.n)
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

        def save() -> None:
            assert checkpoint is not None
            snapshot = (asdict(config), agent, optimizer, rng, resets, state, hf_policy)
            save_checkpoint(checkpoint, Checkpoint.capture(*snapshot, best_agent=best_agent))

        if checkpoint is not None and checkpoint.exists():
            restored = load_checkpoint(checkpoint, asdict(config))
            state = restored.restore(agent, optimizer, rng, resets, hf_policy)
            best_agent = restored.best_agent
            obs, _ = env.reset(seed=state.episode_seed)
            for action in state.episode_actions:  # replay the episode in progress
                obs, *_ = env.step(action)
        else:
            state.episode_seed = resets.next()
            obs, _ = env.reset(seed=state.episode_seed)
            state.episode_is_hf = hf_policy is not None and rng.random() < hf_epsilon(0, config)

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
        truncated_is = config.hf_treatment == "truncated_is"
        n_updates_total = -(-config.total_steps // config.n_steps)
        last_returns: list[float] = []

        while keep_going and state.global_step < config.total_steps:
            # ---- 1. collect n_steps with the behaviour policy (pi_HF or pi_RL per episode) --
            rollout_start = time.perf_counter()
            for t in range(config.n_steps):
                with torch.inference_mode():
                    logits, value = agent(torch.as_tensor(obs))
                    log_probs = torch.log_softmax(logits, dim=-1).numpy()
                if not state.episode_is_hf:
                    action = _sample(np.exp(log_probs.astype(np.float64)), rng)
                    mu_logp = float(log_probs[action])
                elif config.hf_guide_sampling:
                    hf_probs = hf_policy.sampling_probs(obs).astype(np.float64)
                    action = _sample(hf_probs, rng)
                    mu_logp = float(np.log(hf_probs[action]))
                else:
                    action = hf_policy.act(obs)  # greedy pi_HF: mu(a|s) = 1
                    mu_logp = 0.0
                next_obs, reward, terminated, truncated, info = env.step(action)
                reward = float(reward) * config.reward_scale
                if truncated and not terminated:  # time limit: bootstrap the cut-off tail
                    with torch.inference_mode():
                        _, tail_value = agent(torch.as_tensor(next_obs))
                    reward += config.gamma * float(tail_value)
                rollout.obs[t] = obs
                rollout.actions[t] = action
                rollout.pi_logp[t] = log_probs[action]
                rollout.mu_logp[t] = mu_logp
                rollout.is_hf[t] = state.episode_is_hf
                rollout.rewards[t] = reward
                rollout.values[t] = float(value)
                rollout.ends[t] = float(terminated or truncated)
                state.global_step += 1
                state.episode_actions.append(action)
                state.episode_return += float(reward)
                obs = next_obs
                if terminated or truncated:
                    last_returns.append(state.episode_return)
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
                    state.episode_seed = resets.next()
                    state.episode_actions = []
                    state.episode_return = 0.0
                    obs, _ = env.reset(seed=state.episode_seed)
                    state.episode_is_hf = hf_policy is not None and rng.random() < hf_epsilon(
                        state.global_step, config
                    )
                keep_going &= callback.on_step(state.global_step, info)
                if state.global_step % config.eval_every == 0:
                    keep_going &= evaluate()
            rollout_seconds = time.perf_counter() - rollout_start

            # ---- 2. advantages: GAE (authors) or trace-cut GAE + rho weights (truncated_is) -
            with torch.inference_mode():
                _, next_value = agent(torch.as_tensor(obs))
            if truncated_is:
                ratio_to_mu = np.exp(rollout.pi_logp.astype(np.float64) - rollout.mu_logp)
                traces = np.minimum(1.0, ratio_to_mu)
                weights = np.minimum(config.is_clip, ratio_to_mu)
            else:
                traces = None
                weights = np.ones(config.n_steps)
            advantages = compute_advantages(
                rollout.rewards,
                rollout.values,
                rollout.ends,
                float(next_value),
                config.gamma,
                config.gae_lambda,
                traces,
            )
            returns = rollout.values + weights * advantages

            # ---- 3. n_epochs of minibatch updates --------------------------------------------
            # Every epoch's permutation is drawn first (the same draws as one per epoch), then
            # each minibatch is gathered, and its advantages normalised, by one op per rollout.
            update_start = time.perf_counter()
            order = np.concatenate(
                [rng.permutation(config.n_steps) for _ in range(config.n_epochs)]
            )
            index = torch.from_numpy(order).view(-1, config.minibatch_size)
            mb_adv = torch.from_numpy(advantages.astype(np.float32))[index]
            if config.norm_adv and config.minibatch_size > 1:
                mb_adv = (mb_adv - mb_adv.mean(1, keepdim=True)) / (
                    mb_adv.std(1, keepdim=True) + 1e-8
                )
            minibatches = zip(  # the arguments of ppo_loss, one row per minibatch
                torch.from_numpy(rollout.obs)[index],
                torch.from_numpy(rollout.actions)[index],
                torch.from_numpy(rollout.pi_logp)[index],
                mb_adv,
                torch.from_numpy(returns.astype(np.float32))[index],
                torch.from_numpy(weights.astype(np.float32))[index]
                if truncated_is
                else [None] * len(index),  # all weights 1: skip the multiplication
                strict=True,
            )
            if config.anneal_lr:  # linear to 0 over the run, from the update count
                optimizer.lr = config.learning_rate * (1.0 - state.n_updates / n_updates_total)
            n_minibatches = config.n_steps // config.minibatch_size  # per epoch
            early_stop = config.target_kl is not None  # needs every minibatch's approx KL
            stats_sum: dict[str, float] = {}  # loss statistics of the last epoch (begun)
            n_in_epoch = n_done = 0
            for i, minibatch in enumerate(minibatches):
                last_epoch = i >= len(index) - n_minibatches
                if i % n_minibatches == 0:
                    stats_sum, n_in_epoch = {}, 0
                loss, stats = ppo_loss(
                    agent, *minibatch, config, with_stats=last_epoch or early_stop
                )
                for key, val in stats.items():
                    stats_sum[key] = stats_sum.get(key, 0.0) + val
                n_in_epoch += 1
                if early_stop and stats["losses/approx_kl"] > config.target_kl:
                    break  # this minibatch is already too far from the rollout policy
                optimizer.zero_grad()
                loss.backward()
                optimizer.clip_grad_norm_(config.max_grad_norm)
                optimizer.step()
                n_done += 1
            state.n_updates += 1
            metrics = {key: val / max(n_in_epoch, 1) for key, val in stats_sum.items()}
            metrics["losses/update_epochs"] = n_done / n_minibatches
            metrics.update(
                _update_metrics(
                    config,
                    state,
                    rollout,
                    returns,
                    last_returns,
                    hf_policy is not None,
                    optimizer.lr,
                )
            )
            metrics["charts/SPS"] = config.n_steps / max(time.perf_counter() - rollout_start, 1e-9)
            metrics["charts/rollout_seconds"] = rollout_seconds
            metrics["charts/update_seconds"] = time.perf_counter() - update_start
            last_returns = []
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


def _update_metrics(
    config: PPOConfig,
    state: RunState,
    rollout: Rollout,
    returns: np.ndarray,
    last_returns: list[float],
    guided: bool,
    learning_rate: float,
) -> dict[str, float]:
    """CleanRL-named metrics of an update besides the loss statistics."""
    var_returns = float(np.var(returns))
    explained = 1.0 - float(np.var(returns - rollout.values)) / var_returns if var_returns else None
    return {
        "global_step": float(state.global_step),
        "losses/explained_variance": float("nan") if explained is None else explained,
        "charts/eps_hf": hf_epsilon(state.global_step, config) if guided else 0.0,
        "charts/hf_step_fraction": float(np.mean(rollout.is_hf)) if guided else 0.0,
        "charts/episodic_return": float(np.mean(last_returns)) if last_returns else float("nan"),
        "charts/learning_rate": learning_rate,
    }
