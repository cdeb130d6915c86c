"""Stage 2 of Brain-Guided RL: the feedback model Fhat and the human-feedback policy pi_HF.

Akinola et al., "Accelerated Robot Learning via Human Brain Signals", ICRA 2020,
§Human Feedback Policy and Algorithm 1 (``Train the HF policy``).

* :class:`FeedbackModel` is Fhat: observation (13) -> hidden (16, tanh) -> one logit per
  action. ``sigmoid(Fhat(s)[a])`` is the predicted probability that ``a`` is judged correct.
  Training uses binary cross-entropy on the output of the *taken* action only
  (:func:`services.learner.hf_methods.label_nll`, ``paper``).
* :class:`~services.learner.feedback_buffer.FeedbackReplayBuffer` keeps every training
  label. The "newer is more important" rule (from the authors' code): each replay
  minibatch is, with probability ``newest_fraction`` (0.3), the ``batch_size`` newest
  labels, otherwise a uniform sample of all labels, so the newest labels are replayed far
  more often than old ones.
* :class:`FeedbackLearner` applies Algorithm 1's update per label: one SGD step on the new
  label, then ``replay_updates`` (K_HF) minibatch steps from the buffer. Every label is held
  out for validation with probability ``validation_fraction`` (0.2) and never trained on.
* :class:`~services.learner.collection.HFPolicy` samples from
  ``softmax(beta * sigmoid(Fhat(s)))`` (beta = 8) while labels are collected, so the labelled
  actions stay diverse, and acts greedily (``argmax_a Fhat(s, a)``, the paper's pi_HF) when it
  guides RL; :class:`~services.learner.collection.CollectionRule` is each method's rule for
  the labelled action (both importable from here too).
* ``FeedbackConfig.method`` names the stage-2 method (:mod:`services.learner.hf_methods`):
  the paper's BCE (``paper``, the default), a noise-aware or categorical likelihood, active
  queries from a bootstrapped ensemble.
* :func:`collect_feedback` takes labels from any
  :class:`~services.learner.feedback_sources.FeedbackSource` (the noisy oracle, decoded EEG,
  stored labels).
* ``FeedbackConfig.label_channel`` says how a label enters Fhat's update: ``hard``, the
  thresholded label under the label-noise model (g, b) (the paper); ``soft``, the decoder's
  calibrated likelihood ratio ``lambda = P(epoch | error) / P(epoch | correct)``. A soft
  label is a "correct" label whose per-label accuracy is ``r = 1 / (1 + lambda)`` (P(correct |
  epoch) at even odds): the likelihood of the epoch given that the action is optimal with
  probability p is proportional to ``r p + (1 - r)(1 - p)``, which is the hard label's
  ``g p + (1 - b)(1 - p)`` with g = b = r; the paper's BCE takes r as its target.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from services.core.actions import N_ACTIONS
from services.core.feedback import LABEL_CHANNELS
from services.learner.collection import CollectionRule, HFPolicy
from services.learner.feedback_buffer import NO_SOFT_LABEL, FeedbackRecord, FeedbackReplayBuffer
from services.learner.feedback_sources import FeedbackSource, unpack_label
from services.learner.hf_methods import (
    DEFAULT_ASSUMED_ACCURACY,
    FhatEnsemble,
    get_method,
    label_nll,
    mean_label_loss,
    optimality,
)
from services.learner.kernel_prior import KernelEvidence
from services.learner.networks import ObsNormalizer, layer_init
from services.learner.query import PathPosterior, PathQuery


@dataclass
class FeedbackConfig:
    """Hyperparameters of Fhat, its replay buffer and pi_HF."""

    hidden_size: int = 16
    """Width of Fhat's single hidden layer (paper: 16)."""
    lr: float = 1e-3
    """Adam learning rate of Fhat."""
    replay_updates: int = 16
    """K_HF: replay minibatch updates after each new training label."""
    batch_size: int = 32
    """Replay minibatch size."""
    newest_fraction: float = 0.3
    """Probability that a replay minibatch is the newest ``batch_size`` labels."""
    validation_fraction: float = 0.2
    """Probability that a label is held out for validation instead of trained on."""
    beta: float = 8.0
    """Inverse temperature of the sampling policy softmax(beta * sigmoid(Fhat))."""
    method: str = "paper"
    """Stage-2 method (:data:`services.learner.hf_methods.HF_METHODS`); ``paper`` = BCE."""
    good_accuracy: float | None = None
    """Label-noise model: P(label "correct" | optimal action); None = 0.6 assumed."""
    bad_accuracy: float | None = None
    """Label-noise model: P(label "error" | sub-optimal action); None = 0.6 assumed."""
    ensemble_size: int = 5
    """Members of the bootstrapped ensemble of the active-query methods."""
    thompson_period: int = 20
    """Collection actions between two Thompson draws of the member to follow."""
    revisit_window: int = 24
    """``greedy`` collection: an observation seen in this many last collection actions is a
    loop, where the softmax is sampled instead of the argmax (24: two full turns in place)."""
    kernel_bandwidth: float = 0.1
    """``kernel`` prior: bandwidth h of the Gaussian kernel on the normalised observations
    (per dimension, on [-1, 1]; :mod:`services.learner.kernel_prior`)."""
    label_channel: str = "hard"
    """``hard``: the thresholded label under the noise model; ``soft``: the decoder's
    calibrated likelihood ratio (each label must carry one)."""
    query_certainty: float = 0.95
    """``bayes`` collection: a state whose MAP action has this posterior is crossed without
    a label (:mod:`services.learner.query`)."""
    query_cell_m: float = 0.3
    """``bayes`` collection: the state cell size in m (one forward move)."""
    query_fit_period: int = 25
    """``bayes``: Fhat is fitted to the posterior after every this many training labels (the
    posterior, not Fhat, chooses the queries, so Fhat need not follow every label)."""
    query_fit_steps: int = 50
    """``bayes``: full-batch Adam steps of each periodic fit."""
    query_final_fit_steps: int = 1500
    """``bayes``: full-batch Adam steps of the fit at the end of collection."""

    def __post_init__(self) -> None:
        get_method(self.method)  # ValueError naming the known methods
        if self.label_channel not in LABEL_CHANNELS:
            raise ValueError(
                f"unknown label_channel {self.label_channel!r}; expected one of {LABEL_CHANNELS}"
            )
        for name in ("good_accuracy", "bad_accuracy"):
            value = getattr(self, name)
            if value is not None and not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        good, bad = self.noise_model
        if get_method(self.method).uses_noise_model and good + bad <= 1.0:
            raise ValueError(
                f"good_accuracy + bad_accuracy must exceed 1 for method {self.method!r} "
                f"(labels must carry information), got {good} + {bad}"
            )
        if not 0.5 < self.query_certainty < 1.0 or self.query_cell_m <= 0:
            raise ValueError("query_certainty must be in (0.5, 1) and query_cell_m > 0")
        if self.query_fit_period < 1 or min(self.query_fit_steps, self.query_final_fit_steps) < 0:
            raise ValueError("query_fit_period must be >= 1, the fit steps >= 0")
        if self.kernel_bandwidth <= 0:
            raise ValueError(f"kernel_bandwidth must be > 0, got {self.kernel_bandwidth}")
        if self.ensemble_size < 2 or self.thompson_period < 1 or self.revisit_window < 1:
            raise ValueError("ensemble_size must be >= 2, thompson_period and revisit_window >= 1")
        if self.hidden_size < 1 or self.batch_size < 1 or self.replay_updates < 0:
            raise ValueError("hidden_size and batch_size must be >= 1, replay_updates >= 0")
        if not 0.0 <= self.newest_fraction <= 1.0:
            raise ValueError(f"newest_fraction must be in [0, 1], got {self.newest_fraction}")
        if not 0.0 <= self.validation_fraction < 1.0:
            raise ValueError(
                f"validation_fraction must be in [0, 1), got {self.validation_fraction}"
            )

    @property
    def noise_model(self) -> tuple[float, float]:
        """(good, bad) per-class label accuracies, 0.6 where none was given."""
        good = DEFAULT_ASSUMED_ACCURACY if self.good_accuracy is None else self.good_accuracy
        bad = DEFAULT_ASSUMED_ACCURACY if self.bad_accuracy is None else self.bad_accuracy
        return good, bad


@dataclass(frozen=True)
class Minibatch:
    """One update's labels: their rows in the buffer (the new label's row is the one it is
    stored at), observations, actions, hard labels and soft labels (None on the hard
    channel)."""

    rows: np.ndarray
    obs: torch.Tensor
    actions: torch.Tensor
    labels: torch.Tensor
    p_correct: torch.Tensor | None = None

    def targets(
        self, likelihood: str, noise_model: tuple[float, float]
    ) -> tuple[torch.Tensor, float | torch.Tensor, float | torch.Tensor]:
        """(labels, good, bad) the loss reads: a soft label is "correct" at per-label
        accuracy r (the BCE's target is r itself), a hard one has the noise model's."""
        if self.p_correct is None:
            return self.labels, *noise_model
        p = self.p_correct
        return (p if likelihood == "bce" else torch.ones_like(p)), p, p


class FeedbackModel(nn.Module):
    """Fhat(s, .): fixed normalisation -> Linear(n_obs, hidden) -> tanh -> Linear(hidden, 3).

    Parameters
    ----------
    normalizer : ObsNormalizer
        Fixed observation normalisation (part of the model).
    hidden_size : int
        Width of the hidden layer (paper: 16).
    n_actions : int
        Number of discrete actions (one output each).
    """

    def __init__(
        self, normalizer: ObsNormalizer, hidden_size: int = 16, n_actions: int = N_ACTIONS
    ) -> None:
        super().__init__()
        self.normalizer = normalizer
        self.hidden = layer_init(nn.Linear(normalizer.n_obs, hidden_size))
        self.output = layer_init(nn.Linear(hidden_size, n_actions), std=1.0)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Logits of "action judged correct", shape (..., n_actions)."""
        # .forward: nn.Module's call machinery costs ~1 us a submodule, and stage 2 calls
        # this once per label for the collection action and once per update step
        return self.output.forward(torch.tanh(self.hidden.forward(self.normalizer.forward(obs))))


class FeedbackLearner:
    """Online training of Fhat from a stream of labels (Algorithm 1, stage 2)."""

    def __init__(
        self, normalizer: ObsNormalizer, config: FeedbackConfig | None = None, seed: int = 0
    ) -> None:
        self.config = config or FeedbackConfig()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.model = FeedbackModel(normalizer, self.config.hidden_size)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.config.lr)
        self.buffer = FeedbackReplayBuffer(normalizer.n_obs)
        self.rng = np.random.default_rng(seed)
        self.validation: list[FeedbackRecord] = []
        self._validation_cache: tuple[int, Any] | None = None
        self.n_updates = 0
        self.method = get_method(self.config.method)
        self.policy = HFPolicy(self.model, self.config.beta, self.config.method)
        self.ensemble: FhatEnsemble | None = None
        self.kernel: KernelEvidence | None = None
        if self.method.prior == "kernel":
            self.kernel = KernelEvidence(
                normalizer.n_obs, self.config.kernel_bandwidth, self.config.noise_model
            )
        self.query: PathQuery | None = None
        """The ``bayes`` collection's posterior and query rule (:mod:`services.learner.query`)."""
        if self.method.collection == "bayes":
            self.query = PathQuery(
                PathPosterior(self.method.prior),
                self.config.query_certainty,
                self.config.query_cell_m,
                self.config.noise_model,
            )
        if self.method.uses_ensemble:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed + 1)
                self.ensemble = FhatEnsemble(
                    normalizer, self.config.ensemble_size, self.config.hidden_size, N_ACTIONS
                )
            self.ensemble_optimizer = torch.optim.Adam(
                self.ensemble.parameters(), lr=self.config.lr
            )
            # bootstrap weights (0 or 2 per member and label) from their own stream, so the
            # validation split and replay batches match the paper's for the same labels
            self.ensemble_rng = np.random.default_rng([seed, 2])
            self.bootstrap = np.zeros((len(self.buffer.labels), self.config.ensemble_size))
        self.collection = CollectionRule(
            self.method,
            self.policy,
            self.ensemble,
            self.config.noise_model,
            self.config.thompson_period,
            self.config.revisit_window,
        )
        """The method's rule for the labelled action (:mod:`services.learner.collection`)."""

    def loss(self, minibatch: Minibatch) -> torch.Tensor:
        """Fhat's loss on ``minibatch`` (the method's likelihood or the kernel posterior's
        cross-entropy)."""
        labels, good, bad = minibatch.targets(self.method.likelihood, self.config.noise_model)
        if self.kernel is not None:
            log_q = torch.log_softmax(self.model(minibatch.obs), dim=-1)
            return -(self.kernel.posterior(minibatch.rows) * log_q).sum(dim=-1).mean()
        logits = self.model(minibatch.obs)
        return mean_label_loss(logits, minibatch.actions, labels, self.method.likelihood, good, bad)

    def step(self, minibatch: Minibatch) -> float:
        """One update of Fhat (and the ensemble) on ``minibatch``; the loss."""
        rows, obs, actions = minibatch.rows, minibatch.obs, minibatch.actions
        labels, good, bad = minibatch.targets(self.method.likelihood, self.config.noise_model)
        likelihood = self.method.likelihood
        loss = self.loss(minibatch)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        self.n_updates += 1
        if self.ensemble is not None:
            weights = torch.from_numpy(self.bootstrap[rows].T).float()  # (K, N)
            nll = label_nll(self.ensemble(obs), actions, labels, likelihood, good, bad)
            member_loss = (weights * nll).mean(dim=1).sum()
            self.ensemble_optimizer.zero_grad(set_to_none=True)
            member_loss.backward()
            self.ensemble_optimizer.step()
        return float(loss.detach())

    def collection_action(self, obs: np.ndarray, rng: np.random.Generator) -> int:
        """The action to execute (and so to label) while labels are collected: the method's
        :class:`~services.learner.collection.CollectionRule` (``paper``-style methods sample
        pi_HF, softmax(beta * P(optimal))); the ``bayes`` rule's
        :class:`~services.learner.query.PathQuery`)."""
        if self.query is not None:
            return self.query.action(obs, rng)
        return self.collection.action(obs, rng)

    @property
    def wants_label(self) -> bool:
        """Whether the last collection action is to be labelled (False: a ``bayes`` transit
        move across a state the posterior is certain of)."""
        return self.query is None or self.query.wants_label

    @property
    def leaves_path(self) -> bool:
        """Whether the last label's action left the believed path (``bayes``: restart)."""
        return self.query is not None and self.query.leaves_path

    @property
    def soft(self) -> bool:
        """True on the ``soft`` label channel."""
        return self.config.label_channel == "soft"

    def add(
        self,
        obs: np.ndarray,
        action: int,
        label: bool,
        optimal: bool | None = None,
        log_likelihood_ratio: float | None = None,
    ) -> FeedbackRecord:
        """Route a label to validation or training; a training label triggers 1 + K_HF steps
        (``bayes``: no hold-out; the posterior is updated and Fhat refitted every
        ``query_fit_period`` labels).

        ``log_likelihood_ratio`` (``log P(epoch | error) / P(epoch | correct)``) is the soft
        label: required on the ``soft`` channel, recorded but unused on the ``hard`` one.
        """
        record, minibatches = self.route(obs, action, label, optimal, log_likelihood_ratio)
        for minibatch in minibatches:
            self.step(minibatch)
        return record

    def route(
        self,
        obs: np.ndarray,
        action: int,
        label: bool,
        optimal: bool | None = None,
        log_likelihood_ratio: float | None = None,
    ) -> tuple[FeedbackRecord, Iterator[Minibatch]]:
        """:meth:`add` without its updates: the label's record and the minibatches of its
        1 + K_HF steps (none for a validation label), for the caller to step on, in order
        (the new label, then each replay minibatch; a lockstep batch of learners steps
        them together, :mod:`services.learner.feedback_lockstep`). The generator stores the
        label and draws each replay batch as it is advanced, so the draws are the same
        however the steps are taken."""
        if self.soft and log_likelihood_ratio is None:
            raise ValueError(
                "the soft label channel needs each label's log-likelihood ratio (a calibrated "
                "decoder's); this label is hard only (the noisy oracle gives hard labels)"
            )
        if log_likelihood_ratio is not None and not np.isfinite(log_likelihood_ratio):
            raise ValueError(f"log_likelihood_ratio must be finite, got {log_likelihood_ratio}")
        obs = np.asarray(obs, dtype=np.float32)
        # the bayes posterior is exact: every label informs it (no hold-out)
        is_validation = self.query is None and bool(
            self.rng.random() < self.config.validation_fraction
        )
        record = FeedbackRecord(
            obs=obs.tolist(),
            action=int(action),
            label=bool(label),
            optimal=None if optimal is None else bool(optimal),
            validation=is_validation,
            log_likelihood_ratio=(
                None if log_likelihood_ratio is None else float(log_likelihood_ratio)
            ),
        )
        if is_validation:
            self.validation.append(record)
            return record, iter(())
        if self.query is not None:
            # the posterior (which the next action and the restart depend on) now; Fhat's
            # periodic fit when the caller advances the (empty) minibatch stream
            llr = log_likelihood_ratio if self.soft else None
            self.query.row_cells.append(self.query.add(obs, action, label, llr))
            soft = NO_SOFT_LABEL if llr is None else soft_label(llr)
            self.buffer.add(obs, action, label, soft)
            return record, self._posterior_fit()
        return record, self._training_minibatches(obs, action, label, log_likelihood_ratio)

    def _posterior_fit(self) -> Iterator[Minibatch]:
        """``bayes``: no minibatch; Fhat is refitted to the posterior every
        ``query_fit_period`` training labels when the stream is advanced."""
        if self.buffer.size % self.config.query_fit_period == 0:
            self.fit_posterior(self.config.query_fit_steps)
        yield from ()

    def fit_posterior(self, steps: int, optimizer: torch.optim.Optimizer | None = None) -> None:
        """``bayes``: ``steps`` full-batch Adam steps of Fhat's cross-entropy to the posterior
        of every training label's state, each state weighted equally (however many labels
        it took), so pi_HF = argmax Fhat follows the posterior's MAP where labels were taken
        and generalises elsewhere; nothing for other methods."""
        if self.query is None or self.buffer.size == 0:
            return
        optimizer = optimizer or self.optimizer
        rows = np.arange(self.buffer.size)
        obs = torch.from_numpy(self.buffer.obs[rows])
        target = self.query.targets(rows)
        cells = np.asarray(self.query.row_cells)
        weight = torch.from_numpy(1.0 / np.bincount(cells)[cells]).float()
        weight /= weight.sum()
        for _ in range(steps):
            log_q = torch.log_softmax(self.model(obs), dim=-1)
            loss = -(weight * (target * log_q).sum(dim=-1)).sum()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            self.n_updates += 1

    def finish(self) -> None:
        """End of collection: ``bayes`` fits Fhat to the final posterior
        (``query_final_fit_steps``, a fresh Adam at :data:`QUERY_FINAL_FIT_LR`); nothing for
        other methods."""
        if self.query is not None:
            fit = torch.optim.Adam(self.model.parameters(), lr=QUERY_FINAL_FIT_LR)
            self.fit_posterior(self.config.query_final_fit_steps, fit)

    def _training_minibatches(
        self, obs: np.ndarray, action: int, label: bool, log_likelihood_ratio: float | None
    ) -> Iterator[Minibatch]:
        """The new training label's minibatch, then (with the label stored) K_HF replay
        minibatches drawn from the buffer."""
        if self.ensemble is not None:
            self.bootstrap[self.buffer.size] = 2.0 * self.ensemble_rng.integers(
                0, 2, self.config.ensemble_size
            )
        p_correct = None
        if self.soft:
            assert log_likelihood_ratio is not None
            p_correct = soft_label(log_likelihood_ratio)
        if self.kernel is not None:
            x = self.model.normalizer(torch.from_numpy(obs)).numpy()
            self.kernel.add(x, action, label, p_correct)
        yield Minibatch(
            np.array([self.buffer.size]),
            torch.from_numpy(obs[None]),
            torch.tensor([int(action)]),
            torch.tensor([float(label)]),
            None if p_correct is None else torch.tensor([p_correct], dtype=torch.float32),
        )
        self.buffer.add(obs, action, label, NO_SOFT_LABEL if p_correct is None else p_correct)
        for _ in range(self.config.replay_updates):
            indices = self.buffer.sample_indices(
                self.rng, self.config.batch_size, self.config.newest_fraction
            )
            soft = self.buffer.soft_tensor(indices) if self.soft else None
            yield Minibatch(indices, *self.buffer.tensors(indices), soft)

    def state_dict(self) -> dict[str, Any]:
        """Everything :meth:`add` depends on: weights, optimiser, buffer, validation, RNG.

        A learner restored with :meth:`load_state_dict` continues exactly as this one would
        (the same updates for the same labels); the result loads with
        ``torch.load(..., weights_only=True)``.
        """
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "buffer": self.buffer.state_dict(),
            "validation": {
                "obs": torch.tensor([r.obs for r in self.validation], dtype=torch.float32),
                "actions": torch.tensor([r.action for r in self.validation], dtype=torch.int64),
                "labels": torch.tensor([r.label for r in self.validation], dtype=torch.bool),
                "optimal": torch.tensor(  # -1 unknown, 0 sub-optimal, 1 optimal
                    [-1 if r.optimal is None else int(r.optimal) for r in self.validation],
                    dtype=torch.int8,
                ),
            },
            "rng": self.rng.bit_generator.state,
            "n_updates": self.n_updates,
            **self._ensemble_state(),
            **({} if self.kernel is None else {"kernel": self.kernel.state_dict()}),
            **({} if self.query is None else {"query": self.query.state_dict()}),
        }

    def _ensemble_state(self) -> dict[str, Any]:
        """The ensemble's state with the collection rule's beside it (top level without one)."""
        if self.ensemble is None:
            return self.collection.state_dict()
        return {
            "ensemble": {
                "model": self.ensemble.state_dict(),
                "optimizer": self.ensemble_optimizer.state_dict(),
                "bootstrap": torch.from_numpy(self.bootstrap[: self.buffer.size].copy()),
                "rng": self.ensemble_rng.bit_generator.state,
                **self.collection.state_dict(),
            }
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the state saved by :meth:`state_dict` (same config and normaliser)."""
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.buffer.load_state_dict(state["buffer"])
        held_out = state["validation"]
        self._validation_cache = None
        self.validation = [
            FeedbackRecord(
                obs=obs,
                action=action,
                label=label,
                optimal=None if optimal < 0 else bool(optimal),
                validation=True,
            )
            for obs, action, label, optimal in zip(
                held_out["obs"].reshape(-1, self.buffer.obs.shape[1]).tolist(),
                held_out["actions"].tolist(),
                held_out["labels"].tolist(),
                held_out["optimal"].tolist(),
                strict=True,
            )
        ]
        self.rng.bit_generator.state = state["rng"]
        self.n_updates = int(state["n_updates"])
        if self.kernel is not None:
            self.kernel.load_state_dict(state["kernel"])
        if self.query is not None:
            self.query.load_state_dict(state["query"])
        if self.ensemble is None:
            self.collection.load_state_dict(state)
        else:
            ensemble = state["ensemble"]
            self.ensemble.load_state_dict(ensemble["model"])
            self.ensemble_optimizer.load_state_dict(ensemble["optimizer"])
            self.bootstrap[: self.buffer.size] = ensemble["bootstrap"].numpy()
            self.ensemble_rng.bit_generator.state = ensemble["rng"]
            self.collection.load_state_dict(ensemble)

    def validation_accuracy(self) -> tuple[float | None, float | None]:
        """Accuracy of ``P(a optimal) > 0.5`` on held-out labels: (noisy, true).

        P(optimal) is the method's: ``sigmoid(Fhat(s)[a])`` (the paper), a softmax for the
        categorical methods.

        The second figure uses the oracle's truth and is None when no truth is known.
        """
        if not self.validation:
            return None, None
        obs, actions, noisy, mask, truth = self._validation_arrays()
        with torch.no_grad():
            p_optimal = optimality(self.model(obs), self.method.likelihood)
        predicted = (p_optimal.gather(-1, actions.unsqueeze(-1)).squeeze(-1) > 0.5).numpy()
        acc_noisy = float(np.mean(predicted == noisy))
        if not mask.any():
            return acc_noisy, None
        return acc_noisy, float(np.mean(predicted[mask] == truth))

    def _validation_arrays(
        self,
    ) -> tuple[torch.Tensor, torch.Tensor, np.ndarray, np.ndarray, np.ndarray]:
        """The held-out labels as (obs, actions, labels, truth known, truth), rebuilt only
        when a label was held out since the last call (an online session asks after every
        label)."""
        if self._validation_cache is None or self._validation_cache[0] != len(self.validation):
            held_out = self.validation
            known = [r for r in held_out if r.optimal is not None]
            self._validation_cache = (
                len(held_out),
                (
                    torch.tensor([r.obs for r in held_out], dtype=torch.float32),
                    torch.tensor([r.action for r in held_out]),
                    np.array([r.label for r in held_out]),
                    np.array([r.optimal is not None for r in held_out]),
                    np.array([bool(r.optimal) for r in known]),
                ),
            )
        return self._validation_cache[1]


@dataclass
class HFResult:
    """Outcome of a feedback session (stage 2)."""

    model: FeedbackModel
    config: FeedbackConfig
    records: list[FeedbackRecord]
    n_steps: int
    n_episodes: int
    validation_accuracy_noisy: float | None
    validation_accuracy_true: float | None
    label_accuracy: float | None
    """Fraction of received labels that match the oracle's truth (the realised C)."""
    wall_seconds: float

    @property
    def policy(self) -> HFPolicy:
        """The greedy-capable pi_HF built on this Fhat."""
        return HFPolicy(self.model, self.config.beta, self.config.method)

    def summary(self) -> dict[str, Any]:
        """JSON-able figures (no model weights, no records)."""
        return {
            "n_labels": len(self.records),
            "n_steps": self.n_steps,
            "n_episodes": self.n_episodes,
            "validation_accuracy_noisy": self.validation_accuracy_noisy,
            "validation_accuracy_true": self.validation_accuracy_true,
            "label_accuracy": self.label_accuracy,
            "wall_seconds": self.wall_seconds,
            "config": asdict(self.config),
        }


QUERY_FINAL_FIT_LR = 1e-2
"""Adam learning rate of the ``bayes`` methods' final fit of Fhat to the posterior (a
fresh optimiser: a few thousand full-batch steps on at most a few hundred states)."""
SOFT_LABEL_FLOOR = 1e-6
"""A soft label's P(correct | epoch) is kept within [floor, 1 - floor] (a log-likelihood
ratio beyond +-13.8), so that no single epoch is certain evidence."""


def soft_label(log_likelihood_ratio: float) -> float:
    """P(correct | epoch) at even odds, ``1 / (1 + lambda)``, from ``log lambda``."""
    p = 1.0 / (1.0 + np.exp(np.clip(log_likelihood_ratio, -700.0, 700.0)))
    return float(np.clip(p, SOFT_LABEL_FLOOR, 1.0 - SOFT_LABEL_FLOOR))


def sampling_rng(seed: int) -> np.random.Generator:
    """The generator pi_HF samples its actions from while labels of seed ``seed`` are collected.

    Separate from the learner's own generator (validation split, replay minibatches), so the
    actions drawn do not depend on how many replay batches the labels caused.
    """
    return np.random.default_rng([seed, 1])


def _optimal_now(env: gym.Env, action: int) -> bool | None:
    oracle_actions = getattr(env.unwrapped, "optimal_actions", None)
    return None if oracle_actions is None else action in oracle_actions()


class FeedbackCollection:
    """One stage-2 session in progress: its env, source, learner and sampling generator, the
    records so far. :func:`collect_feedback` runs one to the end; a lockstep batch
    (:mod:`services.learner.feedback_lockstep`) advances many, label by label.

    Parameters are :func:`collect_feedback`'s (``max_steps`` already resolved).
    """

    def __init__(
        self,
        env: gym.Env,
        source: FeedbackSource,
        n_labels: int,
        config: FeedbackConfig,
        seed: int,
        max_steps: int,
        on_label: Callable[[FeedbackRecord], None] | None = None,
        on_learner: Callable[[FeedbackLearner], None] | None = None,
    ) -> None:
        if n_labels < 1:
            raise ValueError(f"n_labels must be >= 1, got {n_labels}")
        self.start = time.perf_counter()
        self.env, self.source, self.n_labels = env, source, n_labels
        self.config, self.max_steps, self.on_label = config, max_steps, on_label
        self.on_learner = on_learner
        self.finished = False
        self.learner = FeedbackLearner(
            ObsNormalizer.from_space(env.observation_space), config, seed
        )
        self.rng = sampling_rng(seed)
        self.obs, _ = env.reset(seed=seed)
        self.records: list[FeedbackRecord] = []
        self.n_steps, self.n_episodes = 0, 1

    @property
    def done(self) -> bool:
        """True once every label has arrived."""
        return len(self.records) >= self.n_labels

    def next_label(self) -> Iterator[Minibatch]:
        """Act and step until the next label arrives; its minibatches (none for a
        validation label), to be stepped on before the next call (see
        :meth:`FeedbackLearner.route`)."""
        while True:
            if self.n_steps >= self.max_steps:
                raise RuntimeError(
                    f"only {len(self.records)}/{self.n_labels} labels arrived in "
                    f"{self.max_steps} steps"
                )
            obs = self.obs
            action = self.learner.collection_action(obs, self.rng)
            optimal = _optimal_now(self.env, action)
            next_obs, _, terminated, truncated, _ = self.env.step(action)
            self.n_steps += 1
            # a bayes transit move is not labelled (nobody is asked)
            wanted = self.learner.wants_label
            label = self.source.feedback(obs, action, optimal) if wanted else None
            self.obs = next_obs
            minibatches = None
            if label is not None:
                correct, log_likelihood_ratio = unpack_label(label)
                record, minibatches = self.learner.route(
                    obs, action, correct, optimal, log_likelihood_ratio
                )
                self.records.append(record)
                if self.on_label is not None:
                    self.on_label(record)
            if terminated or truncated or (label is not None and self.learner.leaves_path):
                self.obs, _ = self.env.reset()
                self.n_episodes += 1
                if self.learner.query is not None:
                    self.learner.query.new_episode()
            if minibatches is not None:
                return minibatches

    def run(self) -> HFResult:
        """Collect the remaining labels alone, each label's updates as it arrives; the
        outcome."""
        while not self.done:
            for minibatch in self.next_label():
                self.learner.step(minibatch)
            if self.on_learner is not None:
                self.on_learner(self.learner)
        return self.result()

    def result(self) -> HFResult:
        """The session's outcome (Fhat as trained so far, every record, the accuracies);
        the first call finishes the learner (:meth:`FeedbackLearner.finish`)."""
        if not self.finished:
            self.learner.finish()
            self.finished = True
        known = [r for r in self.records if r.optimal is not None]
        label_accuracy = float(np.mean([r.label == r.optimal for r in known])) if known else None
        acc_noisy, acc_true = self.learner.validation_accuracy()
        return HFResult(
            model=self.learner.model,
            config=self.config,
            records=self.records,
            n_steps=self.n_steps,
            n_episodes=self.n_episodes,
            validation_accuracy_noisy=acc_noisy,
            validation_accuracy_true=acc_true,
            label_accuracy=label_accuracy,
            wall_seconds=time.perf_counter() - self.start,
        )


def default_max_steps(config: FeedbackConfig, n_labels: int) -> int:
    """Env steps after which a collection gives up: ``10 * n_labels``, ``200 * n_labels``
    for the ``bayes`` collection (its transit moves are steps without a label)."""
    return (200 if get_method(config.method).collection == "bayes" else 10) * n_labels


def collect_feedback(
    env: gym.Env,
    source: FeedbackSource,
    n_labels: int = 1000,
    *,
    config: FeedbackConfig | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    on_label: Callable[[FeedbackRecord], None] | None = None,
    on_learner: Callable[[FeedbackLearner], None] | None = None,
) -> HFResult:
    """Run Algorithm 1's stage 2: act with pi_HF (sampling), label, update Fhat.

    Parameters
    ----------
    env : gymnasium.Env
        The task; if it has ``optimal_actions()``, the oracle's truth is recorded per label.
    source : FeedbackSource
        Where the feedback comes from.
    n_labels : int
        Labels to collect (training and validation together).
    config : FeedbackConfig, optional
        Fhat and buffer hyperparameters.
    seed : int
        Seeds Fhat's initialisation, the sampling, the validation split and the first reset.
    max_steps : int, optional
        Give up after this many env steps (default ``10 * n_labels``, ``200 * n_labels``
        for the ``bayes`` collection's transit moves) if labels go missing.
    on_label : callable, optional
        Called with each new record, before its updates (progress bars, persistence).
    on_learner : callable, optional
        Called with the learner after each label's updates (a study measures a copy of
        pi_HF at several budgets in one collection: a budget's labels are the first of a
        larger one).

    Returns
    -------
    HFResult
        The trained Fhat, every record and the validation accuracies.
    """
    config = config or FeedbackConfig()
    max_steps = default_max_steps(config, n_labels) if max_steps is None else max_steps
    collection = FeedbackCollection(
        env, source, n_labels, config, seed, max_steps, on_label, on_learner
    )
    return collection.run()
