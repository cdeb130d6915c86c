"""Where one lockstep PPO minibatch step goes: 20 runs, minibatch 64, synthetic data.

Usage (from the repository root): ``PYTHONPATH=. python
docs/results/bench_sweep/h23d/minibatch_step.py``. Prints the process CPU time of each part
of ``lockstep_update``'s step (instrumented in place, 300 steps after 50 of warm-up), then
the same kernels alone on hot caches.
"""

import collections
import time
from collections.abc import Callable

import numpy as np
import torch

from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig
from services.learner.ppo.lockstep import BatchedActorCritic, BatchedAdam
from services.learner.ppo.update import ppo_loss

torch.set_num_threads(1)
N, B, K, STEPS = 20, 64, 32, 300
torch.manual_seed(0)
agents = [ActorCritic(ObsNormalizer(np.zeros(13), np.ones(13)), 3, (64, 64)) for _ in range(N)]
model = BatchedActorCritic(agents)
optimizer = BatchedAdam(model, [FlatAdam(a.parameters(), lr=3e-4, eps=1e-5) for a in agents])
config = PPOConfig()
g = torch.Generator().manual_seed(1)
obs = torch.randn(K, N, B, 13, generator=g) * 3
actions = torch.randint(0, 3, (K, N, B), generator=g)
old_logp = torch.full((K, N, B), -1.1)
adv = torch.randn(K, N, B, generator=g)
ret = torch.randn(K, N, B, generator=g)
prior_weight = torch.zeros(N)
spent: dict[str, float] = collections.defaultdict(float)
clock = time.process_time


def forward(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """BatchedActorCritic.forward, each op timed."""
    t0 = clock()
    x = (x - model.offset) / model.scale
    n, batch, n_obs = x.shape
    h = x.unsqueeze(1).expand(n, 2, batch, n_obs).reshape(2 * n, batch, n_obs)
    spent["forward: normalise + expand"] += clock() - t0
    for k, (weight, bias, activate) in enumerate(model.layers):
        t0 = clock()
        h = torch.baddbmm(bias, h, weight)
        t1 = clock()
        spent[f"forward: baddbmm layer {k + 1}"] += t1 - t0
        if activate:
            h = torch.tanh(h)
            spent[f"forward: tanh layer {k + 1}"] += clock() - t1
    out = h.view(n, 2, batch, -1)
    return out[:, 0], out[:, 1, :, 0]


model.forward = forward  # type: ignore[method-assign]


def step(i: int, timed: bool) -> None:
    i %= K
    t0 = clock()
    loss, _ = ppo_loss(
        model, obs[i], actions[i], old_logp[i], adv[i], ret[i], None, config, None,
        prior_weight, with_stats=False,
    )  # fmt: skip
    t1 = clock()
    optimizer.zero_grad()
    t2 = clock()
    loss.sum().backward()
    t3 = clock()
    optimizer.clip_grad_norm_(config.max_grad_norm)
    t4 = clock()
    optimizer.step(None)
    t5 = clock()
    if timed:
        for name, dt in (
            ("ppo_loss (forward included)", t1 - t0), ("zero_grad", t2 - t1),
            ("backward", t3 - t2), ("clip_grad_norm_", t4 - t3), ("Adam step", t5 - t4),
            ("STEP", t5 - t0),
        ):  # fmt: skip
            spent[name] += dt


for i in range(50):
    step(i, False)
spent.clear()
for i in range(STEPS):
    step(i, True)
print(f"in context, {N} runs, minibatch {B}: CPU us per step")
for name, total in spent.items():
    print(f"  {name:32s} {total / STEPS * 1e6:8.1f}")


def alone(name: str, f: Callable[[], object], reps: int = 300) -> None:
    for _ in range(20):
        f()
    t0 = clock()
    for _ in range(reps):
        f()
    print(f"  {name:32s} {(clock() - t0) / reps * 1e6:8.1f}")


a, w = torch.randn(2 * N, B, 64), torch.randn(2 * N, 64, 64)
bias, grad = torch.randn(2 * N, 1, 64), torch.randn(2 * N, B, 64)
y = torch.tanh(torch.randn(2 * N, B, 64))
x13, w13 = torch.randn(2 * N, B, 13), torch.randn(2 * N, 13, 64)
flat = [torch.randn(model.flat_params.numel()) for _ in range(5)]
p, gr, m, v, d = flat[0], flat[1], flat[2], flat[3].abs(), flat[4]
print("alone (hot caches): CPU us per call")
alone("baddbmm 64x64 (layer 2)", lambda: torch.baddbmm(bias, a, w))
alone("baddbmm 13x64 (layer 1)", lambda: torch.baddbmm(bias, x13, w13))
alone("bmm x^T g (weight grad)", lambda: torch.bmm(a.transpose(1, 2), grad))
alone("bmm g W^T (input grad)", lambda: torch.bmm(grad, w.transpose(1, 2)))
alone("tanh (40, 64, 64)", lambda: torch.tanh(a))
alone("tanh_backward", lambda: torch.ops.aten.tanh_backward(grad, y))


def adam_ops() -> None:
    m.lerp_(gr, 0.1)
    v.mul_(0.999).addcmul_(gr, gr, value=0.001)
    torch.sqrt(v, out=d)
    d.div_(0.99).add_(1e-5)
    p.addcdiv_(m, d, value=-1e-4)


alone(f"Adam's 7 ops, {p.numel()} floats", adam_ops)
