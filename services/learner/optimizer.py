"""PPO's optimiser: global gradient-norm clipping and Adam on one flat parameter buffer.

The plain equivalent is ``nn.utils.clip_grad_norm_`` followed by ``torch.optim.Adam`` (the
tests check :class:`FlatAdam` against exactly that, to a tolerance); this one runs each op
once on a flat buffer instead of once per parameter, which is most of the cost of an
optimiser step on PPO's tiny networks.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import nn


class FlatAdam:
    """Gradient-norm clipping and Adam over parameters gathered into one flat buffer.

    The same arithmetic as ``nn.utils.clip_grad_norm_`` then ``torch.optim.Adam``
    (single-tensor path, no weight decay), but each op runs once on the flat buffer instead
    of once per parameter: per-op overhead is most of an optimiser step on tiny networks.
    Results agree with torch's to float rounding (vectorised kernels may group a flat
    buffer's elements differently from per-parameter tensors).

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


def adam_update_(
    params: Sequence[torch.Tensor],
    grads: Sequence[torch.Tensor],
    exp_avg: Sequence[torch.Tensor],
    exp_avg_sq: Sequence[torch.Tensor],
    n_steps: int,
    lr: float,
    betas: tuple[float, float],
    eps: float,
    denom: Sequence[torch.Tensor] | None = None,
) -> None:
    """One Adam step in place on the given tensors (one list entry per parameter):
    ``torch.optim.Adam``'s single-tensor arithmetic (no weight decay), :meth:`FlatAdam.step`'s,
    for callers that keep their own moments (the lockstep batches of PPO and of Fhat);
    ``denom``, buffers shaped like ``params`` to hold the denominators (else allocated).

    Each op runs on every tensor of the lists in one ``torch._foreach_*`` call: on the CPU
    that is the same elementwise kernel per tensor (the same values) without a Python call
    per tensor."""
    beta1, beta2 = betas
    torch._foreach_lerp_(exp_avg, grads, 1 - beta1)
    torch._foreach_mul_(exp_avg_sq, beta2)
    torch._foreach_addcmul_(exp_avg_sq, grads, grads, value=1 - beta2)
    bias_correction1 = 1 - beta1**n_steps
    bias_correction2 = 1 - beta2**n_steps
    if denom is None:
        denom = torch._foreach_sqrt(exp_avg_sq)
    else:  # no foreach sqrt with out=; a copy then sqrt_ would cost a pass more
        for buffer, squares in zip(denom, exp_avg_sq, strict=True):
            torch.sqrt(squares, out=buffer)
    torch._foreach_div_(denom, bias_correction2**0.5)
    torch._foreach_add_(denom, eps)
    torch._foreach_addcdiv_(params, exp_avg, denom, value=-lr / bias_correction1)
