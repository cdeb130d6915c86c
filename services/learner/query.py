"""Stage 2's Bayesian query method: spend labels where they inform about the way to the goal.

Issue #24, item 3. At C = 0.6 a label carries 0.029 bits; the softmax and on-policy rules
spend most of them on states already known (the early path, relabelled every episode) or
off the path. The ``bayes`` collection (:data:`services.learner.hf_methods.HF_METHODS`
``bayes_query`` and ``bayes_query_flat``) keeps an exact posterior per state and asks only
where it is uncertain:

* **State.** The pose cell an observation was taken at (BrainNav's
  ``observation_cell(obs, cell_m)``: position relative to the goal on a ``cell_m`` grid and
  the heading; other observations: their values on a ``cell_m`` grid), so VSSG's jittered
  starts share their cells.
* **Evidence.** Per (state s, action a) the summed log-likelihood ratio of "a is optimal":
  ``log g / (1 - b)`` for a hard "correct" label, ``log (1 - g) / b`` for an "error" one, and
  ``-log lambda`` for a soft label (``lambda = P(epoch | error) / P(epoch | correct)``). With
  one optimal action per state, ``P(k optimal | labels at s)`` is ``softmax(log pi + e[s])``
  (the likelihood of every label under "k optimal", divided by the same constant for all k),
  exactly the Beta/binomial count for hard labels written as log-odds.
* **Prior** (``hierarchical``): which action is optimal is drawn, per state, from one shared
  categorical pi with a Dirichlet(alpha) hyperprior ("mostly forward" is learned, not
  assumed: alpha is weak). A state's prior is pi's posterior mean given the *other* states'
  posteriors (leave-one-out, a few mean-field iterations), so a label enters its own
  state's evidence once and never reaches a neighbour as if it were its own: evidence is
  shared only through pi. ``flat``: the uniform prior.
* **Query rule.** At a visited state whose posterior is certain (max >= ``certainty``) the
  robot executes the MAP action as a *transit* move: it moves, nobody is asked, no label
  is spent. At an uncertain state (or one seen before in the episode: a loop) it executes
  the top-two Thompson sampling action (Russo 2016, beta = 1/2: draw k1 from the posterior;
  half of the time execute it, else redraw until k2 != k1) and asks for a label. If that
  action is not the MAP action after the update, the robot has left the believed path and
  the episode restarts (labels there would be off-path).
  An episode that ends without a label (every state on the way certain) raises the
  threshold just above its least certain state, which the next episode asks about.
* **pi_HF.** Fhat (the 13 -> 16 -> 3 MLP) is trained with cross-entropy to the posterior of
  every training label's state (the same 1 + K_HF steps per label as the other methods),
  so pi_HF = argmax Fhat generalises to unseen states and stays what guides RL.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from typing import Any

import numpy as np
import torch
from scipy.special import logsumexp

from services.core.actions import N_ACTIONS, Action
from services.sim.env import OBS_SIZE, BrainNavEnv

QUERY_PRIORS = ("hierarchical", "flat")
MAX_ABS_EVIDENCE = 13.8
"""One label's log-likelihood ratio is kept within +-13.8 (P within 1e-6 of certain), as the
soft channel's :data:`services.learner.feedback.SOFT_LABEL_FLOOR`."""
MEAN_FIELD_ITERATIONS = 3
"""Leave-one-out prior iterations after each label (from the last fixed point)."""


def hard_evidence(label: bool, good: float, bad: float) -> float:
    """Log-likelihood ratio of "the labelled action is optimal" for a hard label."""
    if label:
        return math.log(good / (1.0 - bad))
    return math.log((1.0 - good) / bad)


def soft_evidence(log_likelihood_ratio: float) -> float:
    """``-log lambda`` (``lambda = P(epoch | error) / P(epoch | correct)``), clipped."""
    return float(np.clip(-log_likelihood_ratio, -MAX_ABS_EVIDENCE, MAX_ABS_EVIDENCE))


def state_key(obs: np.ndarray, cell_m: float) -> tuple[int, ...]:
    """The state an observation belongs to: BrainNav's pose cell, else a ``cell_m`` grid."""
    obs = np.asarray(obs, dtype=np.float64)
    if obs.shape == (OBS_SIZE,):
        return BrainNavEnv.observation_cell(obs, cell_m)
    return tuple(int(v) for v in np.floor(obs / cell_m))


def forward_hyperprior(strength: float = 4.0, forward_share: float = 0.5) -> np.ndarray:
    """Dirichlet pseudo-counts alpha over the optimal action: ``strength`` states' worth,
    ``forward_share`` of them on forward (weak: 2 of 4 by default)."""
    alpha = np.full(N_ACTIONS, strength * (1.0 - forward_share) / (N_ACTIONS - 1))
    alpha[int(Action.FORWARD)] = strength * forward_share
    return alpha


def map_log_odds(log_posterior: np.ndarray) -> float:
    """Log-odds of the MAP action, ``log q_max - log(1 - q_max)``, computed in log space
    (finite however certain the posterior)."""
    best = int(np.argmax(log_posterior))
    return float(log_posterior[best] - logsumexp(np.delete(log_posterior, best)))


def top_two_thompson(posterior: np.ndarray, rng: np.random.Generator, beta: float = 0.5) -> int:
    """Top-two Thompson sampling: k1 ~ posterior; with probability ``beta`` k1, else a
    draw from the posterior without k1 (k1 when the posterior is certain of it)."""
    k1 = int(rng.choice(len(posterior), p=posterior))
    if rng.random() < beta:
        return k1
    rest = posterior.copy()
    rest[k1] = 0.0
    if rest.sum() <= 0.0:
        return k1
    return int(rng.choice(len(rest), p=rest / rest.sum()))


class PathPosterior:
    """Per-state posterior of the optimal action from labels' log-likelihood ratios.

    Parameters
    ----------
    prior : str
        ``hierarchical`` (a shared categorical with a Dirichlet ``alpha`` hyperprior, each
        state's prior from the other states) or ``flat`` (uniform).
    alpha : numpy.ndarray, optional
        Dirichlet pseudo-counts (default :func:`forward_hyperprior`).
    """

    def __init__(self, prior: str = "hierarchical", alpha: np.ndarray | None = None) -> None:
        if prior not in QUERY_PRIORS:
            raise ValueError(f"unknown query prior {prior!r}; expected one of {QUERY_PRIORS}")
        self.prior = prior
        self.alpha = forward_hyperprior() if alpha is None else np.asarray(alpha, float)
        if self.alpha.shape != (N_ACTIONS,) or (self.alpha <= 0).any():
            raise ValueError(f"alpha must be {N_ACTIONS} positive pseudo-counts")
        self.index: dict[Hashable, int] = {}
        self.keys: list[Hashable] = []
        self.evidence = np.zeros((0, N_ACTIONS))
        self.n_labels = np.zeros((0, N_ACTIONS), dtype=np.int64)
        self.log_q = np.zeros((0, N_ACTIONS))
        """Log posterior of each known state (rows of ``evidence``)."""

    def __len__(self) -> int:
        return len(self.keys)

    def cell(self, key: Hashable) -> int:
        """Row of ``key``, added (with no evidence) if new."""
        row = self.index.get(key)
        if row is None:
            prior = np.log(self.shared_prior())
            row = self.index[key] = len(self.keys)
            self.keys.append(key)
            self.evidence = np.vstack([self.evidence, np.zeros(N_ACTIONS)])
            self.n_labels = np.vstack([self.n_labels, np.zeros(N_ACTIONS, dtype=np.int64)])
            self.log_q = np.vstack([self.log_q, prior])
        return row

    @property
    def q(self) -> np.ndarray:
        """Posterior of each known state, shape (states, actions)."""
        return np.exp(self.log_q)

    def shared_prior(self) -> np.ndarray:
        """The prior of a state without labels: pi's posterior mean given every state."""
        if self.prior == "flat":
            return np.full(N_ACTIONS, 1.0 / N_ACTIONS)
        labelled = self.n_labels.sum(axis=1) > 0
        counts = self.alpha + self.q[labelled].sum(axis=0)
        return counts / counts.sum()

    def log_priors(self) -> np.ndarray:
        """Each state's log prior, shape (states, actions): leave-one-out for
        ``hierarchical`` (the state's own labels never shape its own prior)."""
        n = len(self.keys)
        if self.prior == "flat":
            return np.full((n, N_ACTIONS), -math.log(N_ACTIONS))
        labelled = (self.n_labels.sum(axis=1) > 0)[:, None]
        total = self.alpha + (self.q * labelled).sum(axis=0)
        loo = total - self.q * labelled
        return np.log(loo) - np.log(loo.sum(axis=1, keepdims=True))

    def _refit(self) -> None:
        for _ in range(MEAN_FIELD_ITERATIONS if self.prior == "hierarchical" else 1):
            z = self.log_priors() + self.evidence
            self.log_q = z - logsumexp(z, axis=1, keepdims=True)

    def add(self, key: Hashable, action: int, evidence: float) -> None:
        """One label of ``action`` at state ``key`` with log-likelihood ratio ``evidence``."""
        if not math.isfinite(evidence):
            raise ValueError(f"evidence must be finite, got {evidence}")
        row = self.cell(key)
        self.evidence[row, action] += evidence
        self.n_labels[row, action] += 1
        self._refit()

    def log_posterior(self, key: Hashable) -> np.ndarray:
        """log P(k optimal | every label) at state ``key`` (the shared prior if unseen)."""
        row = self.index.get(key)
        return np.log(self.shared_prior()) if row is None else self.log_q[row].copy()

    def posterior(self, key: Hashable) -> np.ndarray:
        """P(k optimal | every label) at state ``key`` (the shared prior if unseen)."""
        return np.exp(self.log_posterior(key))

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Keys (int tuples), evidence and counts; the posterior is recomputed on load."""
        return {
            "keys": torch.tensor(self.keys, dtype=torch.int64).reshape(len(self.keys), -1),
            "evidence": torch.from_numpy(self.evidence.copy()),
            "n_labels": torch.from_numpy(self.n_labels.copy()),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the contents with those of :meth:`state_dict`."""
        self.keys = [tuple(int(v) for v in row) for row in state["keys"].tolist()]
        self.index = {key: row for row, key in enumerate(self.keys)}
        self.evidence = state["evidence"].numpy().astype(float).reshape(-1, N_ACTIONS)
        self.n_labels = state["n_labels"].numpy().astype(np.int64).reshape(-1, N_ACTIONS)
        self.log_q = np.full((len(self.keys), N_ACTIONS), -math.log(N_ACTIONS))
        self._refit()


class PathQuery:
    """The ``bayes`` collection rule: transit where certain, top-two Thompson where not.

    Parameters
    ----------
    posterior : PathPosterior
        The per-state posterior (updated by :meth:`add`).
    certainty : float
        A state whose MAP action has at least this posterior is crossed without a label.
    cell_m : float
        State cell size (:func:`state_key`).
    noise_model : (float, float)
        (good, bad) per-class accuracies of hard labels.
    """

    def __init__(
        self,
        posterior: PathPosterior,
        certainty: float,
        cell_m: float,
        noise_model: tuple[float, float],
    ) -> None:
        if not 0.5 < certainty < 1.0:
            raise ValueError(f"certainty must be in (0.5, 1), got {certainty}")
        self.posterior = posterior
        self.certainty = certainty
        self.threshold = math.log(certainty / (1.0 - certainty))
        """MAP log-odds from which a state is crossed without a label; raised above the
        least certain state of an episode that ended without any label, so the remaining
        labels go to the least certain state on the way."""
        self.episode_labels = 0
        self.episode_least_certain = math.inf
        self.cell_m = cell_m
        self.good, self.bad = noise_model
        self.visited: set[Hashable] = set()
        """States visited in the current episode (a revisit is a loop: asked, not crossed)."""
        self.wants_label = True
        """Whether the last chosen action is a query (False: a transit move)."""
        self.leaves_path = False
        """Whether the last labelled action left the MAP path (the episode should restart)."""
        self.row_cells: list[int] = []
        """Posterior row of each training label, in the replay buffer's order."""

    def new_episode(self) -> None:
        """Forget the episode's visited states (after every reset); after an episode without
        a label, raise the threshold just above its least certain state."""
        if self.episode_labels == 0 and math.isfinite(self.episode_least_certain):
            self.threshold = max(self.threshold, self.episode_least_certain + 1e-9)
        self.visited.clear()
        self.leaves_path = False
        self.episode_labels = 0
        self.episode_least_certain = math.inf

    def action(self, obs: np.ndarray, rng: np.random.Generator) -> int:
        """The action to execute at ``obs``; sets :attr:`wants_label`."""
        key = state_key(obs, self.cell_m)
        log_q = self.posterior.log_posterior(key)
        loop = key in self.visited
        self.visited.add(key)
        log_odds = map_log_odds(log_q)
        self.episode_least_certain = min(self.episode_least_certain, log_odds)
        if log_odds >= self.threshold and not loop:
            self.wants_label = False
            return int(np.argmax(log_q))
        self.wants_label = True
        return top_two_thompson(np.exp(log_q - logsumexp(log_q)), rng)

    def add(self, obs: np.ndarray, action: int, label: bool, llr: float | None) -> int:
        """Update the posterior with one label (hard, or soft when ``llr`` is given); set
        :attr:`leaves_path`; return the state's posterior row."""
        key = state_key(obs, self.cell_m)
        evidence = hard_evidence(label, self.good, self.bad) if llr is None else soft_evidence(llr)
        self.posterior.add(key, action, evidence)
        self.episode_labels += 1
        self.leaves_path = action != int(np.argmax(self.posterior.posterior(key)))
        return self.posterior.index[key]

    def targets(self, rows: np.ndarray) -> torch.Tensor:
        """Posterior of the states of the given training labels (Fhat's targets)."""
        cells = np.asarray(self.row_cells)[rows]
        return torch.from_numpy(self.posterior.q[cells]).float()

    def state_dict(self) -> dict[str, Any]:
        """The posterior and the training labels' rows."""
        return {
            "posterior": self.posterior.state_dict(),
            "row_cells": torch.tensor(self.row_cells, dtype=torch.int64),
            "threshold": self.threshold,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.posterior.load_state_dict(state["posterior"])
        self.row_cells = [int(v) for v in state["row_cells"].tolist()]
        self.threshold = float(state["threshold"])
