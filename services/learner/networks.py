"""Small torch building blocks shared by the feedback model and PPO.

The observation normalisation is *fixed* (no running statistics): every bounded dimension of
the observation space is mapped affinely onto [-1, 1] from its declared ``low``/``high``;
unbounded dimensions pass through unchanged. Being fixed, it is identical for Fhat, pi_HF and
every PPO method, and it is saved inside checkpoints and TorchScript exports.

:class:`FlatAdam` is PPO's optimiser: gradient clipping and Adam with torch's numbers at a
fraction of the per-op overhead.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable

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


class FlatAdam:
    """Gradient-norm clipping and Adam over parameters gathered into one flat buffer.

    The same ops in the same order as ``nn.utils.clip_grad_norm_`` then ``torch.optim.Adam``
    (single-tensor path, no weight decay), hence the same numbers, but each op runs once on
    the flat buffer instead of once per parameter: per-op overhead is most of an optimiser
    step on tiny networks. The numbers are bit-identical to torch's when every parameter but
    the last has a size divisible by 32 (a :class:`TwinMLP` with hidden widths divisible by
    16): each element then takes the same vectorised or scalar-remainder kernel path as in
    the per-parameter ops.

    The parameters keep their identity (``module.parameters()``, ``state_dict``); their data
    and gradients become views of :attr:`params` and :attr:`grads` (so never set their
    ``.grad`` to None). :meth:`state_dict` has ``torch.optim.Adam``'s format.
    """

    def __init__(
        self,
        parameters: Iterable[nn.Parameter],
        lr: float,
        eps: float,
        betas: tuple[float, float] = (0.9, 0.999),
    ) -> None:
        self.parameters = list(parameters)
        self.lr, self.eps, self.betas = lr, eps, betas
        self.params = torch.cat([p.detach().reshape(-1) for p in self.parameters])
        self.grads = torch.zeros_like(self.params)
        self.exp_avg = torch.zeros_like(self.params)
        self.exp_avg_sq = torch.zeros_like(self.params)
        self.denom = torch.zeros_like(self.params)
        self.n_steps = 0
        for p, data, grad in zip(
            self.parameters, self._views(self.params), self._views(self.grads), strict=True
        ):
            p.data, p.grad = data, grad
        self.grad_views = [p.grad for p in self.parameters]

    def _views(self, flat: torch.Tensor) -> list[torch.Tensor]:
        """``flat`` cut into tensors shaped like the parameters."""
        sizes = [p.numel() for p in self.parameters]
        return [v.view_as(p) for v, p in zip(flat.split(sizes), self.parameters, strict=True)]

    def zero_grad(self) -> None:
        """Zero every gradient (backward then accumulates into the flat buffer)."""
        if any(p.grad is not g for p, g in zip(self.parameters, self.grad_views, strict=True)):
            raise RuntimeError("a parameter's .grad was replaced; FlatAdam no longer sees it")
        self.grads.zero_()

    def clip_grad_norm_(self, max_norm: float) -> torch.Tensor:
        """``nn.utils.clip_grad_norm_``: norm of the per-parameter norms, scale if above."""
        total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(self.grad_views)))
        # min(max_norm / (total + 1e-6), 1) by the ops Tensor.__rdiv__ runs, minus its wrapper
        self.grads.mul_((total + 1e-6).reciprocal_().mul_(max_norm).clamp_(max=1.0))
        return total

    def step(self) -> None:
        """One Adam step (``torch.optim.Adam._single_tensor_adam``'s arithmetic)."""
        beta1, beta2 = self.betas
        self.n_steps += 1
        self.exp_avg.lerp_(self.grads, 1 - beta1)
        self.exp_avg_sq.mul_(beta2).addcmul_(self.grads, self.grads, value=1 - beta2)
        bias_correction1 = 1 - beta1**self.n_steps
        bias_correction2 = 1 - beta2**self.n_steps
        torch.sqrt(self.exp_avg_sq, out=self.denom)
        self.denom.div_(bias_correction2**0.5).add_(self.eps)
        self.params.addcdiv_(self.exp_avg, self.denom, value=-self.lr / bias_correction1)

    def state_dict(self) -> dict:
        """The state as ``torch.optim.Adam.state_dict()`` would give it."""
        adam = torch.optim.Adam(self.parameters, lr=self.lr, betas=self.betas, eps=self.eps)
        if self.n_steps:
            moments = zip(self._views(self.exp_avg), self._views(self.exp_avg_sq), strict=True)
            for p, (exp_avg, exp_avg_sq) in zip(self.parameters, moments, strict=True):
                adam.state[p] = {
                    "step": torch.tensor(float(self.n_steps)),
                    "exp_avg": exp_avg.clone(),
                    "exp_avg_sq": exp_avg_sq.clone(),
                }
        return adam.state_dict()

    def load_state_dict(self, state_dict: dict) -> None:
        """Restore from :meth:`state_dict` (or ``torch.optim.Adam``'s) output."""
        adam = torch.optim.Adam(self.parameters, lr=self.lr, betas=self.betas, eps=self.eps)
        adam.load_state_dict(state_dict)
        self.n_steps = 0
        self.exp_avg.zero_()
        self.exp_avg_sq.zero_()
        moments = zip(self._views(self.exp_avg), self._views(self.exp_avg_sq), strict=True)
        for p, (exp_avg, exp_avg_sq) in zip(self.parameters, moments, strict=True):
            if p in adam.state:
                self.n_steps = int(adam.state[p]["step"])
                exp_avg.copy_(adam.state[p]["exp_avg"])
                exp_avg_sq.copy_(adam.state[p]["exp_avg_sq"])
