"""A lockstep PPO minibatch step by batch size, and what three changes of it would save.

Usage (from the repository root): ``PYTHONPATH=. python
docs/results/bench_sweep/h23e/minibatch_variants.py N [N ...]``. For each batch size N
(runs, minibatch 64, synthetic data as ``../h23d/minibatch_step.py``), the process CPU time
of one whole minibatch step (``ppo_loss``, zero_grad, backward, clipping, Adam; 400 steps
after 50 of warm-up, three repetitions alternating the variants), for:

* ``base``: the shipped step (``BatchedActorCritic``, ``BatchedAdam``);
* ``fused_adam``: Adam as one ``torch._fused_adam_`` call on the flat buffers (torch's
  fused CPU kernel: one pass instead of seven) -- different rounding, so not shipped;
* ``run_major``: the flat buffers laid out run by run, the clip one norm per run over its
  flat gradients, then ``fused_adam`` -- different rounding (the norm's order too);
* ``tanh_inplace``: ``tanh_`` on the ``baddbmm`` output instead of a new tensor -- the same
  kernel, bit-identical (checked below).

Before timing, each variant's weights after 200 steps are compared with ``base``'s.
"""

import sys
import time

import numpy as np
import torch

from services.learner.networks import ObsNormalizer
from services.learner.optimizer import FlatAdam
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig
from services.learner.ppo.lockstep import BatchedActorCritic, BatchedAdam
from services.learner.ppo.update import ppo_loss

torch.set_num_threads(1)
B, K, STEPS, REPS = 64, 32, 400, 3
VARIANTS = ("base", "fused_adam", "run_major", "tanh_inplace")
clock = time.process_time
config = PPOConfig()


def fused_adam(params, grads, exp_avg, exp_avg_sq, step):
    torch._fused_adam_(
        [params], [grads], [exp_avg], [exp_avg_sq], [], [step], lr=3e-4, beta1=0.9,
        beta2=0.999, weight_decay=0.0, eps=1e-5, amsgrad=False, maximize=False,
    )  # fmt: skip


def run_major(model: BatchedActorCritic, n: int) -> None:
    """Re-lay the flat buffers as (run, tower, the tower's parameters)."""
    tensors = model.tensors()
    per_tower = [t[0].numel() for t in tensors]
    tower = sum(per_tower)
    flat, grads = torch.zeros(n * 2 * tower), torch.zeros(n * 2 * tower)
    offset = 0
    for t, size in zip(tensors, per_tower, strict=True):
        stride = (tower, *torch.empty(t.shape[1:]).stride())
        data = flat.as_strided(t.shape, stride, offset)
        data.copy_(t.detach())
        t.data, t.grad = data, grads.as_strided(t.shape, stride, offset)
        offset += size
    model.flat_params, model.flat_grads = flat, grads


def variant(name: str, n: int, data):
    torch.manual_seed(0)
    agents = [ActorCritic(ObsNormalizer(np.zeros(13), np.ones(13)), 3, (64, 64)) for _ in range(n)]
    model = BatchedActorCritic(agents)
    optimizer = BatchedAdam(model, [FlatAdam(a.parameters(), lr=3e-4, eps=1e-5) for a in agents])
    exp_avg, exp_avg_sq = torch.zeros_like(model.flat_params), torch.zeros_like(model.flat_params)
    step_count = torch.tensor(0.0)

    def shipped_optimiser() -> None:
        optimizer.clip_grad_norm_(config.max_grad_norm)
        optimizer.step(None)

    optimise = shipped_optimiser
    if name == "fused_adam":

        def optimise() -> None:
            optimizer.clip_grad_norm_(config.max_grad_norm)
            step_count.add_(1)
            fused_adam(model.flat_params, model.flat_grads, exp_avg, exp_avg_sq, step_count)

    elif name == "run_major":
        run_major(model, n)
        rows = model.flat_grads.view(n, -1)

        def optimise() -> None:
            total = torch.linalg.vector_norm(rows, dim=1)
            scale = (total + 1e-6).reciprocal_().mul_(config.max_grad_norm).clamp_(max=1.0)
            rows.mul_(scale[:, None])
            step_count.add_(1)
            fused_adam(model.flat_params, model.flat_grads, exp_avg, exp_avg_sq, step_count)

    elif name == "tanh_inplace":

        def forward(x: torch.Tensor):
            x = (x - model.offset) / model.scale
            runs, batch, n_obs = x.shape
            h = x.unsqueeze(1).expand(runs, 2, batch, n_obs).reshape(2 * runs, batch, n_obs)
            for weight, bias, activate in model.layers:
                h = torch.baddbmm(bias, h, weight)
                if activate:
                    h = torch.tanh_(h)
            out = h.view(runs, 2, batch, -1)
            return out[:, 0], out[:, 1, :, 0]

        model.forward = forward  # type: ignore[method-assign]

    obs, actions, old_logp, adv, ret, prior_weight = data

    def step(i: int) -> None:
        i %= K
        loss, _ = ppo_loss(
            model, obs[i], actions[i], old_logp[i], adv[i], ret[i], None, config, None,
            prior_weight, with_stats=False,
        )  # fmt: skip
        model.flat_grads.zero_()
        loss.sum().backward()
        optimise()

    return step, model


def main() -> None:
    for n in [int(a) for a in sys.argv[1:]] or [20]:
        g = torch.Generator().manual_seed(1)
        data = (
            torch.randn(K, n, B, 13, generator=g) * 3,
            torch.randint(0, 3, (K, n, B), generator=g),
            torch.full((K, n, B), -1.1),
            torch.randn(K, n, B, generator=g),
            torch.randn(K, n, B, generator=g),
            torch.zeros(n),
        )
        weights = {}
        for name in VARIANTS:
            step, model = variant(name, n, data)
            for i in range(200):
                step(i)
            weights[name] = torch.cat([t.detach().reshape(-1) for t in model.tensors()])
        times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        for _ in range(REPS):
            for name in VARIANTS:
                step, _ = variant(name, n, data)
                for i in range(50):
                    step(i)
                t0 = clock()
                for i in range(STEPS):
                    step(i)
                times[name].append((clock() - t0) / STEPS * 1e6)
        base = min(times["base"])
        print(f"{n} runs, minibatch {B}: CPU us per minibatch step (3 repetitions; best)")
        for name in VARIANTS:
            same = torch.equal(weights[name], weights["base"])
            best = min(times[name])
            print(
                f"  {name:13s} {' '.join(f'{t:6.0f}' for t in times[name])}  best {best:6.0f}"
                f"  {best / n:6.1f} per run  x{base / best:4.2f}  "
                f"{'bit-identical' if same else 'differs'} after 200 steps"
            )


if __name__ == "__main__":
    main()
