"""The fast PPO path against a plain reference written the CleanRL way.

The reference uses ``nn.Linear`` actor and critic, ``torch.distributions.Categorical``,
``nn.utils.clip_grad_norm_`` and ``torch.optim.Adam``. From the same weights, on the same
rollout and minibatches, both must give the same outputs, losses and updated weights to
float tolerance (the fast path batches the two towers and the optimiser into fewer ops,
which may round differently on another torch build, so no bit equality is asked).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from gymnasium import spaces
from torch import nn
from torch.distributions import Categorical

from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo import ActorCritic, PPOConfig, ppo_loss

N_OBS, N_ACTIONS, N_STEPS, MINIBATCH = 13, 3, 128, 64


class ReferenceAgent(nn.Module):
    """Separate actor and critic MLPs of ``nn.Linear`` layers (CleanRL's ``Agent``)."""

    def __init__(self, normalizer: ObsNormalizer, hidden: tuple[int, ...]) -> None:
        super().__init__()
        self.normalizer = normalizer
        widths = [N_OBS, *hidden]

        def tower(n_out: int) -> nn.Sequential:
            layers: list[nn.Module] = []
            for fan_in, fan_out in itertools.pairwise(widths):
                layers += [nn.Linear(fan_in, fan_out), nn.Tanh()]
            return nn.Sequential(*layers, nn.Linear(widths[-1], n_out))

        self.actor = tower(N_ACTIONS)
        self.critic = tower(1)

    @classmethod
    def copy_of(cls, agent: ActorCritic, hidden: tuple[int, ...]) -> ReferenceAgent:
        """The same function as ``agent``, weight for weight."""
        reference = cls(agent.normalizer, hidden)
        linears = [
            [m for m in tower if isinstance(m, nn.Linear)]
            for tower in (reference.actor, reference.critic)
        ]
        with torch.no_grad():
            for index, layer in enumerate(agent.towers.layers):
                for tower in (0, 1):
                    linear = linears[tower][index]
                    n_out = linear.out_features
                    linear.weight.copy_(layer.weight[tower, :, :n_out].T)
                    linear.bias.copy_(layer.bias[tower, 0, :n_out])
        return reference

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.normalizer(obs)
        return self.actor(x), self.critic(x).squeeze(-1)


def reference_loss(
    agent: ReferenceAgent,
    obs: torch.Tensor,
    actions: torch.Tensor,
    old_logp: torch.Tensor,
    advantages: torch.Tensor,
    returns: torch.Tensor,
    weights: torch.Tensor | None,
    config: PPOConfig,
) -> torch.Tensor:
    """CleanRL's clipped PPO loss, each step's surrogate weighted by ``weights``."""
    logits, value = agent(obs)
    dist = Categorical(logits=logits)
    ratio = (dist.log_prob(actions) - old_logp).exp()
    pg_loss1 = -advantages * ratio
    pg_loss2 = -advantages * torch.clamp(ratio, 1 - config.clip_coef, 1 + config.clip_coef)
    surrogate = torch.max(pg_loss1, pg_loss2)
    pg_loss = (surrogate if weights is None else weights * surrogate).mean()
    v_loss = 0.5 * ((value - returns) ** 2).mean()
    return pg_loss - config.ent_coef * dist.entropy().mean() + config.vf_coef * v_loss


@pytest.mark.parametrize("weighted", [False, True])
def test_fast_ppo_update_matches_the_plain_reference(weighted) -> None:
    config = PPOConfig(max_grad_norm=0.5)  # small: the clip is active
    space = spaces.Box(low=-np.ones(N_OBS, np.float32), high=np.ones(N_OBS, np.float32) * 3)
    torch.manual_seed(0)
    agent = ActorCritic(ObsNormalizer.from_space(space), N_ACTIONS, config.hidden_sizes)
    reference = ReferenceAgent.copy_of(agent, config.hidden_sizes)
    generator = torch.Generator().manual_seed(1)
    obs = torch.rand(N_STEPS, N_OBS, generator=generator) * 4 - 1
    with torch.no_grad():
        logits, values = agent(obs)
        ref_logits, ref_values = reference(obs)
    assert torch.allclose(logits, ref_logits, atol=1e-6)
    assert torch.allclose(values, ref_values, atol=1e-6)
    initial_logits = logits
    actions = torch.randint(0, N_ACTIONS, (N_STEPS,), generator=generator)
    old_logp = Categorical(logits=logits).log_prob(actions) - 0.1  # ratios away from 1
    advantages = torch.randn(N_STEPS, generator=generator)
    returns = values + torch.randn(N_STEPS, generator=generator)
    weights = torch.rand(N_STEPS, generator=generator) if weighted else None

    fast = FlatAdam(agent.parameters(), lr=config.learning_rate, eps=config.adam_eps)
    adam = torch.optim.Adam(reference.parameters(), lr=config.learning_rate, eps=config.adam_eps)
    order = torch.randperm(N_STEPS * 4, generator=generator) % N_STEPS  # 4 epochs' minibatches
    for index in order.view(-1, MINIBATCH):
        batch = (
            obs[index], actions[index], old_logp[index], advantages[index], returns[index],
            None if weights is None else weights[index],
        )  # fmt: skip
        loss, _ = ppo_loss(agent, *batch, config)
        fast.zero_grad()
        loss.backward()
        fast.clip_grad_norm_(config.max_grad_norm)
        fast.step()
        ref = reference_loss(reference, *batch, config)
        adam.zero_grad()
        ref.backward()
        nn.utils.clip_grad_norm_(reference.parameters(), config.max_grad_norm)
        adam.step()
        assert float(loss.detach()) == pytest.approx(float(ref.detach()), rel=1e-5, abs=1e-6)
    with torch.no_grad():
        logits, values = agent(obs)
        ref_logits, ref_values = reference(obs)
    assert float((logits - initial_logits).abs().max()) > 1e-3  # the updates moved the policy
    assert torch.allclose(logits, ref_logits, atol=1e-5)
    assert torch.allclose(values, ref_values, atol=1e-5)
