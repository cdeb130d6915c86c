"""Stage 2 of many runs in lockstep: :func:`collect_feedback_lockstep`.

Alone, a run's stage 2 makes 1 + K_HF = 17 Adam steps of Fhat (13 -> 16 -> 3) per training
label, ~13,600 for 1000 labels, and nearly all of its time is the per-operation overhead
of those steps (the env steps and the collection rule are a few per cent; measured in
docs/benchmarks.md, "Sweeps in lockstep"). Here the Fhats of N runs are one
:class:`BatchedFhat` (weights of shape (N, fan_out, fan_in), one ``baddbmm`` per layer for
all runs) trained by one Adam over those tensors, so that overhead is paid once for N.

Rounds. Each round, every run advances its own env (its
:class:`~services.learner.feedback.FeedbackCollection`: its collection rule, sampling
generator, source, learner generator, validation split, replay buffer, kernel evidence)
until its next *training* label arrives; then all runs take that label's 1 + K_HF steps
together. Every run so makes one Adam step at every step of the batch (Adam's step count
is common), and a run's Fhat is the same at each of its collection actions as alone (its
model's parameters are views of its row of the batch). A run whose labels are all in
leaves the batch; one that raises leaves it with its exception as its outcome.

Same science. Each run's Fhat, records and figures are bit-identical to
:func:`~services.learner.feedback.collect_feedback` alone (tested per method and label
channel): every op computes each run's slice with the single run's arithmetic
(``baddbmm``'s matrices are separate GEMMs, reductions run along each run's row, Adam is
elementwise), with one exception that is handled: torch's ``sigmoid`` on CPU takes a
vectorised exponential for whole blocks of ``2 x`` the SIMD width of a contiguous tensor
and libm's ``expf`` for the rest, and the two differ in the last bit on ~4 % of inputs; a
run's BCE gradient alone takes the sigmoid of its (batch,) logits, so
:func:`sigmoid_as_alone` gives each run's row what its own tensor would have given.
Methods batched: the ``bce`` and ``categorical`` likelihoods with or without the kernel
prior (``paper``, ``categorical``, ``categorical_onpolicy``, ``categorical_kernel``). The
ensemble methods (their ensemble's updates) and ``noise_aware`` (a sigmoid inside the
loss, through autograd) run alone: :func:`lockstep_feedback_key` is None for them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Any

import torch
from torch import nn

from services.learner.feedback import (
    FeedbackCollection,
    FeedbackConfig,
    FeedbackLearner,
    FeedbackModel,
    HFResult,
    Minibatch,
)
from services.learner.hf_methods import get_method, label_nll
from services.learner.lockstep_batch import leave_batch
from services.learner.optimizer import adam_update_

BATCHED_LIKELIHOODS = ("bce", "categorical")
MIN_BATCHED_LABELS = 9
"""Smallest minibatch whose forward and backward run batched. Below it, torch's ``bmm``
takes a naive loop (under 400 multiply-adds per matrix) and a one-row ``addmm`` is
``mm`` then the bias, neither the single run's arithmetic: each run's own graph is
taken (the new label's step of every label, and the first replay batches)."""
PER_RUN_FEEDBACK_SETTINGS = frozenset({"good_accuracy", "bad_accuracy"})
"""FeedbackConfig fields that may differ between the runs of one lockstep batch, where the
loss does not read them (the ``bce`` likelihood, the kernel prior): the label-noise model."""

SIGMOID_VECTOR_BLOCK = 32 if torch.backends.cpu.get_cpu_capability() == "AVX512" else 16
"""Elements of a contiguous float32 tensor that torch's CPU ``sigmoid`` takes at once with
its vectorised exponential (two SIMD registers: 2 x 16 with AVX-512, 2 x 8 otherwise); the
tail of a tensor shorter than a whole block goes through libm's ``expf``."""


def lockstep_feedback_key(config: FeedbackConfig) -> str | None:
    """Sessions whose configs have equal keys can share a batch (all settings but
    :data:`PER_RUN_FEEDBACK_SETTINGS` equal); None for a method that runs alone."""
    method = get_method(config.method)
    if method.uses_ensemble or method.likelihood not in BATCHED_LIKELIHOODS:
        return None
    if method.collection == "bayes":  # Fhat is fitted to its posterior, not stepped per label
        return None
    shared = asdict(config)
    if method.likelihood == "bce" or method.prior == "kernel":  # the loss has no noise model
        shared = {k: v for k, v in shared.items() if k not in PER_RUN_FEEDBACK_SETTINGS}
    return repr(sorted(shared.items()))


def sigmoid_as_alone(x: torch.Tensor) -> torch.Tensor:
    """``torch.sigmoid`` of each row of ``x`` (runs, n) as it is computed on that row alone
    (a contiguous tensor of n elements), bit for bit.

    Alone, the first ``n // B * B`` elements (B = :data:`SIGMOID_VECTOR_BLOCK`) take the
    vectorised path and the rest the scalar one. Rows of whole blocks stay aligned to the
    blocks in one contiguous tensor; the tail goes through a strided view, which torch's
    elementwise loop takes element by element (the scalar path).
    """
    n = x.shape[-1]
    whole = n // SIGMOID_VECTOR_BLOCK * SIGMOID_VECTOR_BLOCK
    out = torch.empty_like(x)
    if whole:
        out[:, :whole] = torch.sigmoid(x[:, :whole].contiguous())
    if whole < n:
        tail = x[:, whole:]
        spread = x.new_empty(*tail.shape, 2)  # every other element: a non-contiguous view
        spread[..., 0] = tail
        out[:, whole:] = torch.sigmoid(spread[..., 0])
    return out


class BatchedLinear(torch.autograd.Function):
    """``linear`` of each run, (R, B, fan_in) -> (R, B, fan_out), with weights (R, fan_out,
    fan_in) and biases (R, 1, fan_out): ``baddbmm`` forward, and the backward of
    ``linear`` alone per run. torch's own ``bmm`` backward takes the weight's gradient as
    ``x^T @ grad``, where ``linear``'s (``addmm``'s, for a weight in ``nn.Linear``'s
    layout) takes ``grad^T @ x``: the same sums, but another GEMM, whose rounding differs
    for some shapes (Fhat on a 5-dimensional observation).

    ``forward`` takes ``ctx`` itself (no ``setup_context``): torch's ``Function.apply``
    binds the arguments to ``forward``'s signature with ``inspect`` on every call where
    ``setup_context`` is defined, which cost about 8 % of stage 2 in lockstep."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor
    ) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        return torch.baddbmm(bias, x, weight.transpose(1, 2))

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:  # type: ignore[override]
        x, weight = ctx.saved_tensors
        grad_x = torch.bmm(grad, weight) if ctx.needs_input_grad[0] else None
        grad_weight = torch.bmm(grad.transpose(1, 2), x)
        return grad_x, grad_weight, grad.sum(dim=1, keepdim=True)


class BatchedFhat(nn.Module):
    """The Fhats of N runs as one module (run ``r`` is row ``r``); each run's own
    :class:`~services.learner.feedback.FeedbackModel` keeps working on views of its row.

    Weights keep ``nn.Linear``'s layout, (N, fan_out, fan_in): ``baddbmm`` with their
    transpose is, per run, ``linear``'s ``addmm`` with the transposed weight.
    """

    def __init__(self, models: Sequence[FeedbackModel]) -> None:
        super().__init__()
        shapes = {tuple(p.shape for p in m.parameters()) for m in models}
        if len(shapes) != 1:
            raise ValueError("runs of one lockstep batch need Fhats of one shape")
        self.register_buffer("offset", torch.stack([m.normalizer.offset for m in models])[:, None])
        self.register_buffer("scale", torch.stack([m.normalizer.scale for m in models])[:, None])
        self.w1 = nn.Parameter(torch.stack([m.hidden.weight.detach() for m in models]))
        self.b1 = nn.Parameter(torch.stack([m.hidden.bias.detach() for m in models])[:, None])
        self.w2 = nn.Parameter(torch.stack([m.output.weight.detach() for m in models]))
        self.b2 = nn.Parameter(torch.stack([m.output.bias.detach() for m in models])[:, None])
        self.models = list(models)
        self._bind()

    def tensors(self) -> list[nn.Parameter]:
        """The parameters in ``FeedbackModel.parameters()`` order."""
        return [self.w1, self.b1, self.w2, self.b2]

    def _bind(self) -> None:
        """Gather the parameters into :attr:`flat` (each a view of it, in :meth:`tensors`
        order: Adam then runs once on one buffer) and make each run's model's parameters
        views of its row."""
        tensors = self.tensors()
        self.flat = torch.cat([p.detach().reshape(-1) for p in tensors])
        for p, data in zip(tensors, self.flat.split([p.numel() for p in tensors]), strict=True):
            p.data = data.view_as(p)
        self.run_parameters = [list(model.parameters()) for model in self.models]
        """Each run's model's parameters (``parameters()`` walks the module tree per call)."""
        with torch.no_grad():
            for row, theirs_all in enumerate(self.run_parameters):
                for mine, theirs in zip(tensors, theirs_all, strict=True):
                    theirs.data = mine.data[row].view(theirs.shape)

    def forward(self, obs: torch.Tensor, rows: torch.Tensor | None = None) -> torch.Tensor:
        """Logits (R, B, n_actions) of the runs ``rows`` (all if None) for raw observations
        (R, B, n_obs)."""
        offset, scale, w1, b1, w2, b2 = self.offset, self.scale, *self.tensors()
        if rows is not None:
            offset, scale, w1, b1, w2, b2 = (t[rows] for t in (offset, scale, w1, b1, w2, b2))
        x = (obs - offset) / scale
        hidden = torch.tanh(BatchedLinear.apply(x, w1, b1))
        return BatchedLinear.apply(hidden, w2, b2)

    def keep(self, rows: Sequence[int]) -> None:
        """Keep the runs of ``rows`` only (in that order); the models of the others get
        their own copies of their weights and leave the batch."""
        with torch.no_grad():
            for row, model in enumerate(self.models):
                if row not in rows:
                    for p in model.parameters():
                        p.data = p.data.clone()
            index = torch.as_tensor(list(rows), dtype=torch.long)
            self.offset, self.scale = self.offset[index], self.scale[index]
            for name in ("w1", "b1", "w2", "b2"):
                setattr(self, name, nn.Parameter(getattr(self, name).detach()[index].clone()))
        self.models = [self.models[r] for r in rows]
        self._bind()


class BatchedFhatAdam:
    """``torch.optim.Adam`` (single-tensor arithmetic, no weight decay) of every run's Fhat
    at once: the runs step together, so they share one step count. The moments are flat
    buffers laid out as the model's :attr:`~BatchedFhat.flat` (Adam is elementwise: one op
    on the whole batch gives each element the value it has per parameter)."""

    def __init__(self, model: BatchedFhat, lr: float) -> None:
        self.model, self.lr = model, lr
        self.betas, self.eps = (0.9, 0.999), 1e-8
        self._bind(torch.zeros_like(model.flat), torch.zeros_like(model.flat))
        self.n_steps = 0

    def _bind(self, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor) -> None:
        """Take the flat moments and view them per parameter."""
        self.flat_exp_avg, self.flat_exp_avg_sq = exp_avg, exp_avg_sq
        self.denom = torch.empty_like(exp_avg)
        tensors = self.model.tensors()
        sizes = [p.numel() for p in tensors]
        self.exp_avg, self.exp_avg_sq = (
            [v.view_as(p) for v, p in zip(flat.split(sizes), tensors, strict=True)]
            for flat in (exp_avg, exp_avg_sq)
        )

    def keep(self, rows: Sequence[int]) -> None:
        """After ``model.keep(rows)``: keep the moments of ``rows`` only."""
        index = torch.as_tensor(list(rows), dtype=torch.long)
        exp_avg, exp_avg_sq = (
            torch.cat([m[index].reshape(-1) for m in moments])
            for moments in (self.exp_avg, self.exp_avg_sq)
        )
        self._bind(exp_avg, exp_avg_sq)

    @torch.no_grad()
    def step(self, rows: torch.Tensor | None, grads: Sequence[torch.Tensor]) -> None:
        """One Adam step of the runs ``rows`` (all if None) with their gradients (per
        parameter, of ``rows`` only); the step count moves once all runs took this step
        (:meth:`next_step`)."""
        n_steps = self.n_steps + 1
        if rows is None:
            adam_update_(
                [self.model.flat], [torch.cat([g.reshape(-1) for g in grads])],
                [self.flat_exp_avg], [self.flat_exp_avg_sq], n_steps, self.lr, self.betas,
                self.eps, denom=[self.denom],
            )  # fmt: skip
            return
        params = [p.data for p in self.model.tensors()]
        grads = [g if len(g) == len(rows) else g[rows] for g in grads]
        p_rows, m_rows, v_rows = (
            [t[rows] for t in ts] for ts in (params, self.exp_avg, self.exp_avg_sq)
        )
        adam_update_(p_rows, grads, m_rows, v_rows, n_steps, self.lr, self.betas, self.eps)
        for ts, taken in ((params, p_rows), (self.exp_avg, m_rows), (self.exp_avg_sq, v_rows)):
            for t, r in zip(ts, taken, strict=True):
                t[rows] = r

    def next_step(self) -> None:
        """Every run took the current step."""
        self.n_steps += 1

    def write_run_state(self, row: int, optimizer: torch.optim.Optimizer) -> None:
        """Run ``row``'s moments and step count into its own ``torch.optim.Adam``."""
        for p, m, v in zip(
            optimizer.param_groups[0]["params"], self.exp_avg, self.exp_avg_sq, strict=True
        ):
            optimizer.state[p] = {
                "step": torch.tensor(float(self.n_steps)),
                "exp_avg": m[row].clone().view(p.shape),
                "exp_avg_sq": v[row].clone().view(p.shape),
            }


def _step(
    model: BatchedFhat,
    optimizer: BatchedFhatAdam,
    collections: Sequence[FeedbackCollection],
    rows: list[int],
    minibatches: Sequence[Minibatch],
) -> None:
    """One update of the runs ``rows`` (rows of the batch; ``collections`` per row) on
    their minibatches (one each, of one size): :meth:`FeedbackLearner.step`'s arithmetic
    for each. Minibatches smaller than :data:`MIN_BATCHED_LABELS` take each run's own
    forward and backward (see the module doc); the Adam step is the batch's."""
    every = len(rows) == len(collections)
    index = None if every else torch.as_tensor(rows, dtype=torch.long)
    learners = [collections[row].learner for row in rows]
    if len(minibatches[0].rows) < MIN_BATCHED_LABELS:
        grads = []
        for row, learner, minibatch in zip(rows, learners, minibatches, strict=True):
            parameters = model.run_parameters[row]
            for p in parameters:  # zero_grad(set_to_none=True)
                p.grad = None
            learner.loss(minibatch).backward()
            grads.append([p.grad for p in parameters])
        per_parameter = zip(*grads, strict=True)
        shapes = [p.shape[1:] for p in model.tensors()]
        optimizer.step(
            index, [torch.stack(g).view(-1, *s) for g, s in zip(per_parameter, shapes, strict=True)]
        )
    else:
        _batched_backward(model, index, learners, minibatches)
        optimizer.step(index, [p.grad for p in model.tensors()])
    for learner in learners:
        learner.n_updates += 1


def _batched_backward(
    model: BatchedFhat,
    index: torch.Tensor | None,
    learners: Sequence[FeedbackLearner],
    minibatches: Sequence[Minibatch],
) -> None:
    """The gradients of every run's loss on its minibatch in ``model``'s ``.grad``."""
    first = learners[0]
    likelihood = first.method.likelihood
    for p in model.tensors():
        p.grad = None
    obs = torch.stack([mb.obs for mb in minibatches])
    actions = torch.stack([mb.actions for mb in minibatches])
    targets = [mb.targets(likelihood, learner.config.noise_model) for mb, learner in
               zip(minibatches, learners, strict=True)]  # fmt: skip
    logits = model(obs, index)
    if first.kernel is not None:
        posterior = torch.stack(
            [
                learner.kernel.posterior(mb.rows)
                for learner, mb in zip(learners, minibatches, strict=True)
            ]  # type: ignore[union-attr]
        )
        loss = -(posterior * torch.log_softmax(logits, dim=-1)).sum(dim=-1).mean(dim=-1)
        loss.sum().backward()
    elif likelihood == "bce":
        # binary_cross_entropy_with_logits' mean gradient, (sigmoid(x) - y) * 1 / n, taken
        # by hand so that each run's sigmoid is the one of its own tensor
        taken = logits.gather(-1, actions.long().unsqueeze(-1)).squeeze(-1)
        labels = torch.stack([t[0] for t in targets]).float()
        grad = (sigmoid_as_alone(taken.detach()) - labels).div_(taken.shape[-1])
        taken.backward(grad)
    else:
        labels = torch.stack([t[0] for t in targets])
        good, bad = targets[0][1:]
        if isinstance(good, torch.Tensor):  # soft labels: per label
            good = torch.stack([t[1] for t in targets])  # type: ignore[misc]
            bad = torch.stack([t[2] for t in targets])  # type: ignore[misc]
        nll = label_nll(logits, actions, labels, likelihood, good, bad)
        nll.mean(dim=-1).sum().backward()


def collect_feedback_lockstep(
    collections: Sequence[FeedbackCollection],
) -> list[HFResult | Exception]:
    """Run stage-2 sessions in lockstep to their ends; each one's outcome, in order.

    Each outcome is what :func:`~services.learner.feedback.collect_feedback` gives of the
    same session alone (bit-identical, see the module doc), or the exception the session
    raised (it left the batch, the others went on). The sessions must be fresh and share
    :func:`lockstep_feedback_key` (ValueError if not).
    """
    keys = {lockstep_feedback_key(c.config) for c in collections}
    if None in keys or len(keys) > 1:
        raise ValueError(
            "sessions of one lockstep batch need one batched stage-2 method and equal "
            f"settings but {sorted(PER_RUN_FEEDBACK_SETTINGS)} (lockstep_feedback_key)"
        )
    if any(c.records or c.learner.n_updates for c in collections):
        raise ValueError("a lockstep batch starts from fresh sessions")
    outcomes: list[HFResult | Exception | None] = [None] * len(collections)
    if not collections:
        return []
    slots = list(range(len(collections)))  # each batch row's index in collections
    batch = list(collections)
    model = BatchedFhat([c.learner.model for c in batch])
    optimizer = BatchedFhatAdam(model, batch[0].config.lr)

    def leave(keep: list[int], failed: dict[int, Exception]) -> None:
        nonlocal batch, slots
        for row, collection in enumerate(batch):  # a finished run's own Adam state first
            if row not in keep and row not in failed:
                optimizer.write_run_state(row, collection.learner.optimizer)
        batch, slots = leave_batch(
            batch, slots, keep, failed, outcomes, FeedbackCollection.result, (model, optimizer)
        )

    while batch:
        pending: dict[int, list[Minibatch]] = {}
        failed: dict[int, Exception] = {}
        for row, collection in enumerate(batch):
            try:
                while not collection.done and row not in pending:
                    minibatches = list(collection.next_label())
                    if minibatches:  # a training label: its updates are this round's
                        pending[row] = minibatches
            except Exception as exc:  # this run leaves the batch, the others go on
                failed[row] = exc
        keep = sorted(pending)
        leave(keep, failed)
        updates = [pending[row] for row in keep]
        try:
            for j in range(len(updates[0]) if updates else 0):
                sizes: dict[int, list[int]] = {}
                for row, minibatches in enumerate(updates):
                    sizes.setdefault(len(minibatches[j].rows), []).append(row)
                for rows in sizes.values():
                    _step(model, optimizer, batch, rows, [updates[row][j] for row in rows])
                optimizer.next_step()
        except Exception as exc:  # a batched update failed: every run in it fails
            leave([], dict.fromkeys(range(len(batch)), exc))
    return [o if o is not None else RuntimeError("session produced no outcome") for o in outcomes]
