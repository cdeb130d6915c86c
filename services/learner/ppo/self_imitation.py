"""Self-imitation of the episodes that reached the goal (off by default: ``sil_coef = 0``).

Self-imitation learning (SIL, Oh et al., ICML 2018): PPO learns from each transition once,
in the update after it was collected, so in a sparse-reward task the rare early successes
(a random walk's, or a guided episode's) are one batch among hundreds. SIL keeps past
good transitions and, after every PPO update, takes ``sil_updates`` extra minibatch steps on

    L = -log pi(a|s) (R - V(s))+ + 1/2 sil_value_coef ((R - V(s))+)^2,

``R`` the discounted return-to-go of the transition's episode. Where the episode did better
than the value function expects, pi_RL imitates it and V moves up to it; elsewhere the loss
is 0, so the data of any behaviour policy (pi_RL or pi_HF) is safe to use. Here the buffer
holds the transitions of the episodes that reached the goal (``info["is_success"]``), the
only ones with ``R > 0`` under the sparse reward; the oldest are dropped beyond
``sil_capacity`` transitions, and minibatches are drawn uniformly (SIL prioritises by
``(R - V)+``; every stored transition here comes from a success).

A successful episode is read back by replaying its reset seed and actions in a second
environment (the env is deterministic given both), so nothing per step is kept during the
rollout and a resumed run rebuilds nothing.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from services.learner.optimizer import FlatAdam
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig


class SuccessReplay:
    """Transitions of successful episodes with their discounted returns-to-go (FIFO)."""

    def __init__(self, n_obs: int, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.obs = np.zeros((0, n_obs), dtype=np.float32)
        self.actions = np.zeros(0, dtype=np.int64)
        self.returns = np.zeros(0, dtype=np.float32)
        self.capacity = capacity

    def __len__(self) -> int:
        return len(self.actions)

    def add_episode(
        self, obs: np.ndarray, actions: np.ndarray, rewards: np.ndarray, gamma: float
    ) -> None:
        """Store one episode: observations before each action, the actions and the (scaled)
        rewards; returns-to-go are discounted by ``gamma``."""
        returns = np.zeros(len(rewards), dtype=np.float64)
        running = 0.0
        for t in range(len(rewards) - 1, -1, -1):
            running = float(rewards[t]) + gamma * running
            returns[t] = running
        keep = -self.capacity
        self.obs = np.concatenate([self.obs, np.asarray(obs, np.float32)])[keep:]
        self.actions = np.concatenate([self.actions, np.asarray(actions, np.int64)])[keep:]
        self.returns = np.concatenate([self.returns, returns.astype(np.float32)])[keep:]

    def draw(
        self, config: PPOConfig, rng: np.random.Generator
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(observations, actions, returns-to-go) of ``config.minibatch_size`` transitions
        drawn uniformly with replacement."""
        rows = rng.integers(0, len(self), config.minibatch_size)
        return (
            torch.from_numpy(self.obs[rows]),
            torch.from_numpy(self.actions[rows]),
            torch.from_numpy(self.returns[rows]),
        )

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The stored transitions as tensors (for the checkpoint)."""
        return {
            "obs": torch.from_numpy(self.obs.copy()),
            "actions": torch.from_numpy(self.actions.copy()),
            "returns": torch.from_numpy(self.returns.copy()),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the contents with those of :meth:`state_dict`."""
        self.obs = state["obs"].numpy().copy()
        self.actions = state["actions"].numpy().copy()
        self.returns = state["returns"].numpy().copy()


def self_imitation_terms(
    agent: ActorCritic, obs: torch.Tensor, actions: torch.Tensor, returns: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(policy loss, value loss, ``(R - V)+`` per transition) of SIL on a minibatch; for a
    batch of runs every argument has a leading run dimension and the losses are one per run
    (means over the last dimension)."""
    logits, value = agent(obs)
    log_probs = torch.log_softmax(logits, dim=-1)
    logp = log_probs.gather(-1, actions.unsqueeze(-1))
    gap = torch.clamp(returns - value, min=0.0)
    policy_loss = -(logp.squeeze(-1) * gap.detach()).mean(-1)
    value_loss = 0.5 * (gap**2).mean(-1)
    return policy_loss, value_loss, gap


def replay_episode(
    env: gym.Env, seed: int, actions: list[int], reward_scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """(observations before each action, scaled rewards) of the episode that ``env`` plays
    from ``reset(seed=seed)`` with ``actions``."""
    obs, _ = env.reset(seed=seed)
    observations, rewards = [], []
    for action in actions:
        observations.append(obs)
        obs, reward, *_ = env.step(action)
        rewards.append(float(reward) * reward_scale)
    return np.asarray(observations, dtype=np.float32), np.asarray(rewards)


def self_imitation_update(
    agent: ActorCritic,
    optimizer: FlatAdam,
    replay: SuccessReplay,
    config: PPOConfig,
    rng: np.random.Generator,
) -> dict[str, float]:
    """``config.sil_updates`` minibatch steps of the SIL loss on uniform draws from
    ``replay`` (none if it is empty); its mean loss terms as metrics."""
    if len(replay) == 0 or config.sil_updates == 0:
        return {}
    policy_sum = value_sum = positive_sum = 0.0
    for _ in range(config.sil_updates):
        policy_loss, value_loss, gap = self_imitation_terms(agent, *replay.draw(config, rng))
        if bool((gap > 0).any()):  # else the loss is 0: no step (Adam's momentum would move)
            loss = config.sil_coef * (policy_loss + config.sil_value_coef * value_loss)
            optimizer.zero_grad()
            loss.backward()
            optimizer.clip_grad_norm_(config.max_grad_norm)
            optimizer.step()
        policy_sum += policy_loss.item()
        value_sum += value_loss.item()
        positive_sum += (gap > 0).float().mean().item()
    n = config.sil_updates
    return {
        "losses/sil_policy_loss": policy_sum / n,
        "losses/sil_value_loss": value_sum / n,
        "charts/sil_positive_fraction": positive_sum / n,
        "charts/sil_transitions": float(len(replay)),
    }
