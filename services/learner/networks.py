"""Small torch building blocks shared by the feedback model and PPO.

The observation normalisation is *fixed* (no running statistics): every bounded dimension of
the observation space is mapped affinely onto [-1, 1] from its declared ``low``/``high``;
unbounded dimensions pass through unchanged. Being fixed, it is identical for Fhat, pi_HF and
every PPO method, and it is saved inside checkpoints and TorchScript exports.
"""

from __future__ import annotations

import itertools
import math

import gymnasium as gym
import numpy as np
import torch
from torch import nn


class ObsNormalizer(nn.Module):
    """Fixed affine observation normalisation, ``(obs - offset) / scale``.

    Parameters
    ----------
    offset, scale : array-like of shape (n_obs,)
        Per-dimension offset and (positive) scale.
    """

    def __init__(self, offset: np.ndarray, scale: np.ndarray) -> None:
        super().__init__()
        offset = np.asarray(offset, dtype=np.float32)
        scale = np.asarray(scale, dtype=np.float32)
        if offset.shape != scale.shape or offset.ndim != 1:
            raise ValueError(f"offset {offset.shape} and scale {scale.shape} must be equal 1-D")
        if not np.all(scale > 0):
            raise ValueError("every normalisation scale must be positive")
        self.register_buffer("offset", torch.as_tensor(offset))
        self.register_buffer("scale", torch.as_tensor(scale))

    @classmethod
    def from_space(cls, space: gym.spaces.Space) -> ObsNormalizer:
        """Map each finite ``[low, high]`` of a Box onto [-1, 1]; leave infinite dims as is."""
        if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
            raise ValueError(f"expected a 1-D Box observation space, got {space}")
        low = space.low.astype(np.float64)
        high = space.high.astype(np.float64)
        finite = np.isfinite(low) & np.isfinite(high) & (high > low)
        low, high = np.where(finite, low, -1.0), np.where(finite, high, 1.0)
        offset = np.where(finite, (low + high) / 2.0, 0.0)
        scale = np.where(finite, (high - low) / 2.0, 1.0)
        return cls(offset, scale)

    @property
    def n_obs(self) -> int:
        """Number of observation dimensions."""
        return int(self.offset.shape[0])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Normalise a batch (or a single vector) of observations."""
        return (obs - self.offset) / self.scale


def exported_observations(obs: torch.Tensor, n_obs: int) -> torch.Tensor:
    """Raw observations given to an exported (TorchScript) policy, checked and as float32.

    Any float or integer dtype is accepted (numpy's float64 included); the last dimension
    must be ``n_obs``, any leading ones are the batch.
    """
    if obs.dim() == 0 or obs.shape[-1] != n_obs:
        raise ValueError(
            "expected raw observations of shape ("
            + str(n_obs)
            + ",) or (..., "
            + str(n_obs)
            + "), got shape "
            + str(list(obs.shape))
        )
    if obs.is_complex() or obs.dtype == torch.bool:
        raise ValueError("expected real-valued observations, got " + str(obs.dtype))
    return obs.to(torch.float32)


def layer_init(layer: nn.Linear, std: float = math.sqrt(2.0), bias: float = 0.0) -> nn.Linear:
    """Orthogonal weights, constant bias (the CleanRL / SB3 initialisation)."""
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class TwinLayer(nn.Module):
    """One layer of both towers: ``h[t] @ weight[t] + bias[t]`` for t in (0, 1), then tanh."""

    def __init__(self, fan_in: int, fan_out: int, gains: tuple[float, float], activate: bool):
        super().__init__()
        weight = torch.empty(2, fan_in, fan_out)
        for tower in range(2):
            # Same as layer_init(nn.Linear(fan_in, fan_out), gain) on the transposed weight.
            block = torch.empty(fan_out, fan_in)
            nn.init.orthogonal_(block, gains[tower])
            weight[tower] = block.T
        self.weight = nn.Parameter(weight)
        self.bias = nn.Parameter(torch.zeros(2, 1, fan_out))
        self.activate = activate

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """(2, batch, fan_in) -> (2, batch, fan_out)."""
        out = torch.baddbmm(self.bias, h, self.weight)
        return torch.tanh(out) if self.activate else out


class TwinMLP(nn.Module):
    """Two independent tanh MLPs of equal shape evaluated together with batched matmuls.

    Tower 0 is the actor (``n_out`` logits), tower 1 the critic (its first output is the
    value, the other outputs are unused). Mathematically this is two separate networks, as
    in CleanRL/SB3 (separate actor and critic), but one ``baddbmm`` per layer instead of two
    ``Linear`` calls cuts the per-minibatch overhead that dominates tiny networks.

    Parameters
    ----------
    n_in, hidden_sizes, n_out
        Layer widths.
    out_stds
        Orthogonal-init gains of the two output layers (CleanRL: 0.01 actor, 1.0 critic).
    """

    def __init__(
        self,
        n_in: int,
        hidden_sizes: tuple[int, ...],
        n_out: int,
        out_stds: tuple[float, float] = (0.01, 1.0),
    ) -> None:
        super().__init__()
        widths = [n_in, *hidden_sizes, n_out]
        hidden_gain = (math.sqrt(2.0), math.sqrt(2.0))
        self.layers = nn.ModuleList(
            TwinLayer(
                fan_in,
                fan_out,
                out_stds if index == len(widths) - 2 else hidden_gain,
                activate=index < len(widths) - 2,
            )
            for index, (fan_in, fan_out) in enumerate(itertools.pairwise(widths))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Outputs of both towers, shape (2, batch, n_out), for x of shape (batch, n_in)."""
        h = x.unsqueeze(0).expand(2, -1, -1)
        for layer in self.layers:
            h = layer.forward(h)  # not layer(h): nn.Module's call machinery costs ~1 us
        return h
