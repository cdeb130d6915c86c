"""Many PPO runs in lockstep: ``train_lockstep(configs) -> [TrainResult | Exception]``.

A sweep is many small runs of one PPO shape. Alone, a run makes about one Adam step per env
step on two 64-64 MLPs, and most of that step is per-operation overhead, not arithmetic
(docs/benchmarks.md). Here N runs advance together and pay that overhead once:

* their actors and critics are one :class:`BatchedActorCritic` whose layers hold every
  run's two towers (weights of shape (2N, fan_in, fan_out), one ``baddbmm`` per layer for
  all runs); one forward per rollout step gives every run's action distribution;
* their optimisers are one :class:`BatchedAdam` over those tensors: the gradient-norm clip
  is per run (each run's norm of its parameters' norms, as ``FlatAdam``) and Adam is
  elementwise, with each run's own step count and learning rate;
* each run keeps everything else its own (:class:`~services.learner.ppo.run.PPORun`, the
  same code as the single-run :func:`~services.learner.ppo.train`): its env stepped in a
  loop, its random streams, episodes, evaluations, best weights, checkpoints, metrics and
  callbacks; its greedy evaluation episodes are its own too, stepped side by side with
  the other runs' evaluations due at the same step, one batched forward per step
  (:func:`evaluate_lockstep`). Runs that differ in seed, task (env id and
  kwargs: reward, map), evaluation starts, treatment of pi_HF's steps and pi_HF (or none)
  share a batch; every other setting must be equal (:func:`lockstep_key`).

Same science. A run's records in a batch are bit-identical to the single-run path's (tested
on every stabiliser and guidance option): every batched op computes each run's slice with
the arithmetic of the single run (each matrix of a ``baddbmm`` is its own GEMM; means and
norms reduce each run's row alone; Adam is elementwise), and per-run masks replace the
single run's early exits (``target_kl``, self-imitation steps skipped when no transition
beats its value) without touching the other runs. One sum is not guaranteed by torch to
be ordered alike: a run's per-parameter gradient norms are reductions of one row of the
batch here and ``_foreach_norm`` over each tensor in ``FlatAdam``; they agreed bit for bit
in every test (clipping scaled on every step of one), and they can only matter where the
norm exceeds ``max_grad_norm`` (below it, the scale is exactly 1 either way).

Ends. A run whose hook says stop (cancel, a target reached) or whose budget is spent leaves
the batch after its update, as alone; a run that raises leaves it at once and its exception
is its outcome; the others go on. Checkpoints are the single run's format: a run resumes
from its own checkpoint in a batch or alone.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from services.learner.feedback import HFPolicy
from services.learner.lockstep_batch import leave_batch
from services.learner.optimizer import FlatAdam, adam_update_
from services.learner.ppo.advantages import advantages_and_returns
from services.learner.ppo.agent import ActorCritic
from services.learner.ppo.config import PPOConfig
from services.learner.ppo.result import Callback, TrainResult
from services.learner.ppo.rollout import rollout_step
from services.learner.ppo.run import PPORun
from services.learner.ppo.self_imitation import self_imitation_terms
from services.learner.ppo.update import (
    UpdateStats,
    learning_rate,
    minibatches,
    ppo_loss,
)
from services.sim.metrics import spl

PER_RUN_SETTINGS = frozenset({"seed", "env_id", "env_kwargs", "eval_seeds", "hf_treatment"})
"""PPOConfig fields that may differ between the runs of one lockstep batch."""


def lockstep_key(config: PPOConfig) -> str:
    """Runs whose configs have equal keys can share a batch (all settings but
    :data:`PER_RUN_SETTINGS` equal)."""
    shared = {k: v for k, v in asdict(config).items() if k not in PER_RUN_SETTINGS}
    return repr(sorted(shared.items()))


def check_one_shape(configs: Sequence[PPOConfig]) -> None:
    """ValueError unless the configs can share a batch (equal :func:`lockstep_key`), naming
    the first setting in which a run differs from run 0."""
    if len({lockstep_key(c) for c in configs}) <= 1:
        return
    first = asdict(configs[0])
    for index, config in enumerate(configs[1:], start=1):
        for name, value in asdict(config).items():
            if name not in PER_RUN_SETTINGS and repr(value) != repr(first[name]):
                raise ValueError(
                    "runs of one lockstep batch must share every PPO setting but "
                    f"{sorted(PER_RUN_SETTINGS)}; {name}: {first[name]!r} (run 0) but "
                    f"{value!r} (run {index})"
                )


class BatchedActorCritic(nn.Module):
    """The actors and critics of N runs as one module (run ``r`` is row ``r``).

    Same layers as :class:`~services.learner.ppo.agent.ActorCritic` (its twin towers), with
    every run's two towers stacked: layer ``i``'s weight has shape (2N, fan_in, fan_out),
    rows ``2r`` and ``2r + 1`` being run ``r``'s actor and critic; each run keeps its own
    observation normalisation.
    """

    def __init__(self, agents: Sequence[ActorCritic]) -> None:
        super().__init__()
        shapes = {tuple(p.shape for p in a.parameters()) for a in agents}
        if len(shapes) != 1:
            raise ValueError("runs of one lockstep batch need networks of one shape")
        self.register_buffer("offset", torch.stack([a.normalizer.offset for a in agents])[:, None])
        self.register_buffer("scale", torch.stack([a.normalizer.scale for a in agents])[:, None])
        layers = [list(a.towers.layers) for a in agents]
        self.weights = nn.ParameterList(
            torch.cat([run[i].weight.detach() for run in layers]) for i in range(len(layers[0]))
        )
        self.biases = nn.ParameterList(
            torch.cat([run[i].bias.detach() for run in layers]) for i in range(len(layers[0]))
        )
        self.activate = [layer.activate for layer in layers[0]]
        self.flat_params = self.flat_grads = torch.empty(0)
        self.layers: list[tuple[nn.Parameter, nn.Parameter, bool]] = []
        self._bind_flat()

    def _bind_flat(self) -> None:
        """Gather the parameters into :attr:`flat_params` and their gradients into
        :attr:`flat_grads` (each parameter's data and ``.grad`` a view of them, in
        :meth:`tensors` order): the optimiser's elementwise ops then run once on one buffer
        instead of once per parameter."""
        tensors = self.tensors()
        self.flat_params = torch.cat([p.detach().reshape(-1) for p in tensors])
        self.flat_grads = torch.zeros_like(self.flat_params)
        sizes = [p.numel() for p in tensors]
        views = zip(self.flat_params.split(sizes), self.flat_grads.split(sizes), strict=True)
        for p, (data, grad) in zip(tensors, views, strict=True):
            p.data, p.grad = data.view_as(p), grad.view_as(p)
        # (weight, bias, tanh?) per layer, for forward: a ParameterList's iteration goes
        # through its string-keyed __getitem__ (~1% of a lockstep stage 3)
        self.layers = list(zip(self.weights, self.biases, self.activate, strict=True))

    @property
    def n_runs(self) -> int:
        """Runs in the batch."""
        return int(self.offset.shape[0])

    def tensors(self) -> list[nn.Parameter]:
        """The parameters in ``ActorCritic.parameters()`` order (weight, bias per layer)."""
        return [p for pair in zip(self.weights, self.biases, strict=True) for p in pair]

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(action logits (N, B, n_actions), values (N, B)) for raw observations (N, B, n_obs)."""
        x = (obs - self.offset) / self.scale
        n, batch, n_obs = x.shape
        h = x.unsqueeze(1).expand(n, 2, batch, n_obs).reshape(2 * n, batch, n_obs)
        for weight, bias, activate in self.layers:
            h = torch.baddbmm(bias, h, weight)
            if activate:
                h = torch.tanh(h)
        out = h.view(n, 2, batch, -1)
        return out[:, 0], out[:, 1, :, 0]

    @torch.no_grad()
    def copy_run_to(self, row: int, agent: ActorCritic) -> None:
        """Write run ``row``'s weights into ``agent`` (in place)."""
        for mine, theirs in zip(self.tensors(), agent.parameters(), strict=True):
            theirs.copy_(mine[2 * row : 2 * row + 2])

    def keep(self, rows: Sequence[int]) -> None:
        """Keep the runs of ``rows`` only (in that order); the others leave the batch."""
        index = torch.as_tensor(list(rows), dtype=torch.long)
        towers = torch.stack([2 * index, 2 * index + 1], dim=1).reshape(-1)
        self.offset = self.offset[index]
        self.scale = self.scale[index]
        for params in (self.weights, self.biases):
            for i, p in enumerate(params):
                params[i] = nn.Parameter(p.detach()[towers].clone())
        self._bind_flat()


class BatchedAdam:
    """Per-run gradient-norm clipping and Adam over a :class:`BatchedActorCritic`.

    The arithmetic of :class:`~services.learner.optimizer.FlatAdam` for every run: clip each
    run's gradients by the norm of its per-parameter norms, then Adam with each run's own
    step count and learning rate. :meth:`step` moves the runs given only (the others keep
    their weights and moments, as a single run that skips a step). The moments are flat
    buffers laid out as the model's :attr:`~BatchedActorCritic.flat_params`, so a step of
    every run is one op per Adam operation on the whole batch (Adam is elementwise: the
    same values as per parameter).
    """

    def __init__(self, model: BatchedActorCritic, optimizers: Sequence[FlatAdam]) -> None:
        first = optimizers[0]
        self.model = model
        self.betas, self.eps = first.betas, first.eps
        self.n_steps = [0] * len(optimizers)
        self.lr = [first.lr] * len(optimizers)
        self._bind(torch.zeros_like(model.flat_params), torch.zeros_like(model.flat_params))
        for row, optimizer in enumerate(optimizers):
            self.load_run(row, optimizer)

    def _bind(self, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor) -> None:
        """Take the flat moments (laid out as the model's flat parameters) and view them
        per parameter."""
        self.params = self.model.tensors()
        self.flat_exp_avg, self.flat_exp_avg_sq = exp_avg, exp_avg_sq
        self.denom = torch.empty_like(exp_avg)
        sizes = [p.numel() for p in self.params]
        self.exp_avg = [
            v.view_as(p) for v, p in zip(exp_avg.split(sizes), self.params, strict=True)
        ]
        self.exp_avg_sq = [
            v.view_as(p) for v, p in zip(exp_avg_sq.split(sizes), self.params, strict=True)
        ]
        self.grad_views = [p.grad for p in self.params]

    def _rows(self, tensors: list[torch.Tensor]) -> list[torch.Tensor]:
        """Each tensor viewed as (runs, elements of one run)."""
        return [t.view(self.model.n_runs, -1) for t in tensors]

    def load_run(self, row: int, optimizer: FlatAdam) -> None:
        """Take run ``row``'s moments, step count and learning rate from ``optimizer``."""
        sizes = [p.numel() // self.model.n_runs for p in self.params]
        for moments, flat in (
            (self.exp_avg, optimizer.exp_avg),
            (self.exp_avg_sq, optimizer.exp_avg_sq),
        ):
            for mine, theirs in zip(self._rows(moments), flat.split(sizes), strict=True):
                mine[row].copy_(theirs)
        self.n_steps[row], self.lr[row] = optimizer.n_steps, optimizer.lr

    def copy_run_to(self, row: int, optimizer: FlatAdam) -> None:
        """Write run ``row``'s moments, step count and learning rate into ``optimizer``."""
        optimizer.exp_avg.copy_(torch.cat([m[row] for m in self._rows(self.exp_avg)]))
        optimizer.exp_avg_sq.copy_(torch.cat([m[row] for m in self._rows(self.exp_avg_sq)]))
        optimizer.n_steps, optimizer.lr = self.n_steps[row], self.lr[row]

    def keep(self, rows: Sequence[int]) -> None:
        """After ``model.keep(rows)``: keep the state of ``rows`` only."""
        index = torch.as_tensor(list(rows), dtype=torch.long)
        n_before = len(self.n_steps)
        exp_avg, exp_avg_sq = (
            torch.cat([m.view(n_before, -1)[index].reshape(-1) for m in moments])
            for moments in (self.exp_avg, self.exp_avg_sq)
        )
        self.n_steps = [self.n_steps[r] for r in rows]
        self.lr = [self.lr[r] for r in rows]
        self._bind(exp_avg, exp_avg_sq)

    def zero_grad(self) -> None:
        """Zero every gradient (backward then accumulates into the model's flat buffer)."""
        if any(p.grad is not g for p, g in zip(self.params, self.grad_views, strict=True)):
            raise RuntimeError("a parameter's .grad was replaced; BatchedAdam no longer sees it")
        self.model.flat_grads.zero_()

    def clip_grad_norm_(self, max_norm: float) -> torch.Tensor:
        """Per run, ``nn.utils.clip_grad_norm_``: the norm of its per-parameter gradient
        norms, its gradients scaled if above ``max_norm``; the norms, shape (runs,)."""
        grads = self._rows(self.grad_views)
        per_parameter = torch.stack([torch.linalg.vector_norm(g, dim=1) for g in grads], dim=1)
        total = torch.linalg.vector_norm(per_parameter, dim=1)
        scale = (total + 1e-6).reciprocal_().mul_(max_norm).clamp_(max=1.0)[:, None]
        for g in grads:
            g.mul_(scale)
        return total

    @torch.no_grad()
    def step(self, rows: Sequence[int] | None = None) -> None:
        """One Adam step of the runs of ``rows`` (all if None), ``FlatAdam.step``'s
        arithmetic with each run's step count and learning rate."""
        n_runs = len(self.n_steps)
        rows = list(range(n_runs)) if rows is None else list(rows)
        groups: dict[tuple[int, float], list[int]] = {}
        for row in rows:
            self.n_steps[row] += 1
            groups.setdefault((self.n_steps[row], self.lr[row]), []).append(row)
        if len(groups) == 1 and len(rows) == n_runs:  # every run alike: the flat buffers
            (n_steps, lr), _ = groups.popitem()
            adam_update_(
                [self.model.flat_params], [self.model.flat_grads], [self.flat_exp_avg],
                [self.flat_exp_avg_sq], n_steps, lr, self.betas, self.eps, denom=[self.denom],
            )  # fmt: skip
            return
        params = self._rows([p.data for p in self.params])
        grads = self._rows(self.grad_views)
        exp_avg, exp_avg_sq = self._rows(self.exp_avg), self._rows(self.exp_avg_sq)
        for (n_steps, lr), members in groups.items():
            index = torch.as_tensor(members, dtype=torch.long)
            p_rows, m_rows, v_rows = (
                [t[index] for t in ts] for ts in (params, exp_avg, exp_avg_sq)
            )
            g_rows = [g[index] for g in grads]
            adam_update_(p_rows, g_rows, m_rows, v_rows, n_steps, lr, self.betas, self.eps)
            for ts, rows in ((params, p_rows), (exp_avg, m_rows), (exp_avg_sq, v_rows)):
                for t, r in zip(ts, rows, strict=True):
                    t[index] = r


def _stack(arguments: Sequence[Sequence[torch.Tensor | None]], fill: float) -> list[Any]:
    """Each of ``ppo_loss``'s minibatch arguments stacked over runs (leading dimension); an
    argument absent for some runs is ``fill`` there (1: weight 1; 0: a prior of weight 0),
    None where absent for all."""
    stacked: list[Any] = []
    for position, per_run in enumerate(zip(*arguments, strict=True)):
        present = [a for a in per_run if a is not None]
        if not present:
            stacked.append(None)
            continue
        value = 1.0 if position == 5 else fill  # position 5: the surrogate weights
        stacked.append(
            torch.stack(
                [a if a is not None else torch.full_like(present[0], value) for a in per_run]
            )
        )
    return stacked


def lockstep_update(
    model: BatchedActorCritic,
    optimizer: BatchedAdam,
    runs: Sequence[PPORun],
    targets: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
    priors: Sequence[tuple[np.ndarray | None, float]],
) -> list[dict[str, float]]:
    """:func:`~services.learner.ppo.update.update_policy` for every run of the batch at
    once: each run's minibatches from its own generator, its advantages (``targets``: its
    advantages, value targets and surrogate weights), its prior and its learning rate; a
    run stopped by ``target_kl`` takes no further step while the others go on. One metrics
    dict per run."""
    config = runs[0].config
    per_run = [
        minibatches(run.rollout, *target, prior, config=config, rng=run.rng)
        for run, target, (prior, _) in zip(runs, targets, priors, strict=True)
    ]
    obs, actions, old_logp, advantages, returns, weights, prior = _stack(per_run, fill=0.0)
    prior_weight = torch.tensor([weight if p is not None else 0.0 for p, weight in priors])
    for row, run in enumerate(runs):
        optimizer.lr[row] = learning_rate(config, run.state.n_updates)
    early_stop = config.target_kl is not None
    stats = [UpdateStats(config) for _ in runs]
    stepping = list(range(len(runs)))
    n_total = obs.shape[1]
    for i in range(n_total):
        last_epoch = i >= n_total - stats[0].n_minibatches
        loss, mb_stats = ppo_loss(
            model, obs[:, i], actions[:, i], old_logp[:, i], advantages[:, i], returns[:, i],
            None if weights is None else weights[:, i], config,
            None if prior is None else prior[:, i], prior_weight,
            with_stats=last_epoch or early_stop,
        )  # fmt: skip
        still = []
        for row in stepping:
            run_stats = {k: v[row] for k, v in mb_stats.items()}
            if priors[row][0] is None:
                run_stats.pop("losses/hf_prior_cross_entropy", None)
            stats[row].add(i, run_stats)
            if not (early_stop and run_stats["losses/approx_kl"] > config.target_kl):
                still.append(row)
        stepping = still
        if not stepping:
            break
        optimizer.zero_grad()
        (loss.sum() if len(stepping) == len(runs) else loss[stepping].sum()).backward()
        optimizer.clip_grad_norm_(config.max_grad_norm)
        optimizer.step(stepping)
        for row in stepping:
            stats[row].n_done += 1
    return [s.metrics() for s in stats]


def lockstep_self_imitation(
    model: BatchedActorCritic, optimizer: BatchedAdam, runs: Sequence[PPORun]
) -> list[dict[str, float]]:
    """:func:`~services.learner.ppo.self_imitation.self_imitation_update` for every run of
    the batch at once (each from its own buffer and generator; a run steps only where one of
    its transitions beats its value, a run with an empty buffer is left out)."""
    config = runs[0].config
    taking = [
        row
        for row, run in enumerate(runs)
        if run.success_replay is not None and len(run.success_replay) and config.sil_updates
    ]
    metrics: list[dict[str, float]] = [{} for _ in runs]
    if not taking:
        return metrics
    sums = {row: [0.0, 0.0, 0.0] for row in taking}
    for _ in range(config.sil_updates):
        draws = {row: runs[row].success_replay.draw(config, runs[row].rng) for row in taking}
        shape = next(iter(draws.values()))
        filler = tuple(torch.zeros_like(t) for t in shape)  # rows not taking part
        obs, actions, returns = (
            torch.stack([draws.get(row, filler)[k] for row in range(len(runs))]) for k in range(3)
        )
        policy_loss, value_loss, gap = self_imitation_terms(model, obs, actions, returns)
        positive = gap > 0
        stepping = [row for row in taking if bool(positive[row].any())]
        if stepping:
            loss = config.sil_coef * (policy_loss + config.sil_value_coef * value_loss)
            optimizer.zero_grad()
            loss[stepping].sum().backward()
            optimizer.clip_grad_norm_(config.max_grad_norm)
            optimizer.step(stepping)
        policy, value, fraction = (
            policy_loss.tolist(), value_loss.tolist(), positive.float().mean(-1).tolist()
        )  # fmt: skip
        for row in taking:
            sums[row][0] += policy[row]
            sums[row][1] += value[row]
            sums[row][2] += fraction[row]
    for row in taking:
        policy_sum, value_sum, positive_sum = sums[row]
        metrics[row] = {
            "losses/sil_policy_loss": policy_sum / config.sil_updates,
            "losses/sil_value_loss": value_sum / config.sil_updates,
            "charts/sil_positive_fraction": positive_sum / config.sil_updates,
            "charts/sil_transitions": float(len(runs[row].success_replay)),
        }
    return metrics


def evaluate_lockstep(
    model: BatchedActorCritic,
    runs: Sequence[PPORun],
    rows: Sequence[int],
    failed: dict[int, Exception],
) -> None:
    """:meth:`PPORun.evaluate` of the runs of ``rows`` (batch rows, with ``model``'s weights
    theirs): each run plays its greedy episodes from its evaluation starts on its own
    evaluation env, as :func:`~services.learner.evaluation.evaluate_spl`, the runs' episodes
    stepped side by side with one batched forward per step (each row's logits are its own
    GEMMs: the greedy actions of :meth:`PPORun.greedy`). A run that raises goes to
    ``failed``."""
    starts = {row: list(runs[row].config.eval_seeds) for row in rows if row not in failed}
    episodes: dict[int, list[tuple[bool, int, int]]] = {row: [] for row in starts}
    playing: dict[int, list[Any]] = {}  # row -> [observation, shortest steps, steps taken]

    def begin(row: int) -> None:
        obs, info = runs[row].eval_env.reset(seed=starts[row].pop(0))
        playing[row] = [obs, int(info["shortest_path_steps"]), 0]

    for row in list(starts):
        try:
            begin(row)
        except Exception as exc:
            failed[row] = exc
    while playing:
        filler = next(iter(playing.values()))[0]
        obs = np.stack([playing[row][0] if row in playing else filler for row in range(len(runs))])
        with torch.inference_mode():
            actions = model(torch.from_numpy(obs)[:, None])[0][:, 0].argmax(-1).tolist()
        for row in list(playing):
            episode = playing[row]
            try:
                episode[0], _, terminated, truncated, info = runs[row].eval_env.step(actions[row])
                episode[2] += 1
                if terminated or truncated:
                    del playing[row]
                    episodes[row].append(
                        (bool(info.get("is_success", False)), episode[1], episode[2])
                    )
                    if starts[row]:
                        begin(row)
            except Exception as exc:
                playing.pop(row, None)
                failed[row] = exc
    for row, done in episodes.items():
        if row in failed:
            continue
        successes, shortest, taken = zip(*done, strict=True)
        run = runs[row]
        try:
            run.keep_going &= run.record_evaluation(
                float(spl(list(successes), list(shortest), list(taken)))
            )
        except Exception as exc:
            failed[row] = exc


def train_lockstep(
    configs: Sequence[PPOConfig],
    *,
    callbacks: Sequence[Callback | None] | None = None,
    hf_policies: Sequence[HFPolicy | None] | None = None,
    checkpoint_paths: Sequence[str | Path | None] | None = None,
    checkpoint_every: int = 10,
) -> list[TrainResult | Exception]:
    """Train one run per config in lockstep; each run's outcome, in the configs' order.

    Each run is what :func:`~services.learner.ppo.train` would make of its config,
    callback, pi_HF and checkpoint path (bit-identical records, see the module doc); a run
    that raises has its exception as its outcome and leaves the batch, the others go on.
    The configs must share every setting but :data:`PER_RUN_SETTINGS` and the runs their
    checkpoint paths (ValueError if not, before anything runs).
    ``charts/SPS`` and the ``*_seconds`` metrics are the batch's (all runs' steps).
    """
    n = len(configs)
    check_one_shape(configs)
    callbacks = list(callbacks) if callbacks is not None else [None] * n
    hf_policies = list(hf_policies) if hf_policies is not None else [None] * n
    checkpoint_paths = list(checkpoint_paths) if checkpoint_paths is not None else [None] * n
    if not len(callbacks) == len(hf_policies) == len(checkpoint_paths) == n:
        raise ValueError("give one callback, pi_HF and checkpoint path per config (or none)")
    owners: dict[Path, int] = {}  # a shared file would hold one run's state for both
    for index, path in enumerate(checkpoint_paths):
        if path is not None:
            owner = owners.setdefault(Path(path).resolve(), index)
            if owner != index:
                raise ValueError(
                    f"{path}: the checkpoint of runs {owner} and {index}; give each its own"
                )
    outcomes: list[TrainResult | Exception | None] = [None] * n
    with ExitStack() as stack:
        runs: list[PPORun] = []
        slots: list[int] = []  # each batch row's index in configs
        for i, config in enumerate(configs):
            try:
                runs.append(
                    PPORun(
                        config, stack, callback=callbacks[i], hf_policy=hf_policies[i],
                        checkpoint_path=checkpoint_paths[i], checkpoint_every=checkpoint_every,
                        evaluate_first=False,
                    )
                )  # fmt: skip
                slots.append(i)
            except Exception as exc:  # this run ends here, the others go on
                outcomes[i] = exc
        if runs:
            _advance(runs, slots, outcomes)
    return [o if o is not None else RuntimeError("run produced no outcome") for o in outcomes]


def _advance(
    runs: list[PPORun], slots: list[int], outcomes: list[TrainResult | Exception | None]
) -> None:
    """The lockstep loop: rollouts and updates of every run still running, until none is."""
    model = BatchedActorCritic([run.agent for run in runs])
    optimizer = BatchedAdam(model, [run.optimizer for run in runs])
    failed: dict[int, Exception] = {}  # batch row -> what it raised

    def leave(keep: list[int]) -> None:
        nonlocal runs, slots
        runs, slots = leave_batch(
            runs, slots, keep, failed, outcomes, PPORun.finish, (model, optimizer)
        )
        failed.clear()

    def leave_when_done() -> None:
        """The runs whose budget is spent after their last evaluation are evaluated at
        their end (:attr:`PPORun.final_evaluation_due`, as alone); the runs done leave."""
        ends = [
            row for row, run in enumerate(runs) if row not in failed and run.final_evaluation_due
        ]
        if ends:
            evaluate_lockstep(model, runs, ends, failed)
        leave([row for row, run in enumerate(runs) if row not in failed and run.running])

    config = runs[0].config
    first = [row for row, run in enumerate(runs) if not run.state.curve]  # not resumed
    evaluate_lockstep(model, runs, first, failed)
    leave_when_done()  # a run resumed between its last update and its final evaluation
    while runs:
        # ---- 1. rollouts: one batched forward per step, each run's env stepped in turn ------
        rollout_start = time.perf_counter()
        episode_returns: list[list[float]] = [[] for _ in runs]
        successes: list[list[tuple[int, list[int]]]] = [[] for _ in runs]
        for t in range(config.n_steps):
            due: list[int] = []  # rows whose evaluation is due after this step
            with torch.inference_mode():
                obs = torch.from_numpy(np.stack([run.obs for run in runs]))[:, None]
                logits, values = model(obs)
                log_probs = torch.log_softmax(logits[:, 0], dim=-1).numpy()
                values = values[:, 0].tolist()
            for row, run in enumerate(runs):
                if row in failed:
                    continue
                try:
                    step = rollout_step(
                        run.env, run.obs, t, log_probs[row], values[row], run.rollout,
                        run.state, config=run.config, hf_policy=run.hf_policy, rng=run.rng,
                        resets=run.resets, value_of=run.agent.value_of,
                    )  # fmt: skip
                    run.obs = step.obs
                    if step.episode_return is not None:
                        episode_returns[row].append(step.episode_return)
                    if step.success is not None:
                        successes[row].append(step.success)
                    run.keep_going &= run.callback.on_step(run.state.global_step, step.info)
                    if run.state.global_step % run.config.eval_every == 0:
                        due.append(row)
                except Exception as exc:  # this run leaves the batch, the others go on
                    failed[row] = exc
            if due:
                evaluate_lockstep(model, runs, due, failed)
        if failed:
            keep = [row for row in range(len(runs)) if row not in failed]
            episode_returns = [episode_returns[row] for row in keep]
            successes = [successes[row] for row in keep]
            leave(keep)
            if not runs:
                return
        rollout_seconds = time.perf_counter() - rollout_start

        # ---- 2. advantages per run ---------------------------------------------------------
        with torch.inference_mode():
            obs = torch.from_numpy(np.stack([run.obs for run in runs]))[:, None]
            next_values = model(obs)[1][:, 0].tolist()
        targets = [
            advantages_and_returns(run.rollout, next_value, run.config)
            for run, next_value in zip(runs, next_values, strict=True)
        ]

        # ---- 3. the minibatch updates of every run at once -----------------------------------
        update_start = time.perf_counter()
        eps_hf = [run.eps_hf() for run in runs]
        priors = [run.prior(eps) for run, eps in zip(runs, eps_hf, strict=True)]
        metrics = lockstep_update(model, optimizer, runs, targets, priors)
        if config.sil_coef > 0:
            for run, found in zip(runs, successes, strict=True):
                run.remember_successes(found)
            for run_metrics, sil in zip(
                metrics, lockstep_self_imitation(model, optimizer, runs), strict=True
            ):
                run_metrics.update(sil)
        for row, run in enumerate(runs):
            model.copy_run_to(row, run.agent)
            optimizer.copy_run_to(row, run.optimizer)
            try:
                run.end_update(
                    metrics[row], returns=targets[row][1], episode_returns=episode_returns[row],
                    eps_hf=eps_hf[row], rollout_start=rollout_start,
                    rollout_seconds=rollout_seconds, update_start=update_start,
                )  # fmt: skip
            except Exception as exc:
                failed[row] = exc
        leave_when_done()
