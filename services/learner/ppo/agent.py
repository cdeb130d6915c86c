"""pi_RL and its value function: the network PPO trains."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from services.learner.networks import ObsNormalizer, TwinMLP


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

    def value_of(self, obs: np.ndarray) -> float:
        """V of one raw observation (no gradient)."""
        with torch.inference_mode():
            _, value = self.forward(torch.as_tensor(obs))
        return float(value)
