"""Stage 2's collection rules: which action the robot executes, and so which one gets labelled.

Akinola et al. (ICRA 2020, §Human Feedback Policy) sample pi_HF while labels are collected:
:class:`HFPolicy` samples ``softmax(beta * P(optimal))`` (beta = 8) and acts greedily
(``argmax_a Fhat(s, a)``, the paper's pi_HF) when it guides RL. :class:`CollectionRule` picks
the labelled action by the method's ``collection`` (:mod:`services.learner.hf_methods`):

* ``softmax``: sample pi_HF (the paper);
* ``thompson``: follow one bootstrapped ensemble member greedily, redrawn every
  ``thompson_period`` actions;
* ``info``: the plausible action whose label tells most about the ensemble (BALD);
* ``greedy``: pi_HF's argmax, unless the observation is among the last ``revisit_window``
  ones (a loop), where pi_HF is sampled.

The learner (:class:`services.learner.feedback.FeedbackLearner`) trains Fhat and the ensemble;
the rule only reads them.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
import torch
from torch import nn

from services.learner.hf_methods import (
    FhatEnsemble,
    HFMethod,
    get_method,
    most_informative_action,
    optimality,
)


class HFPolicy:
    """pi_HF built on Fhat: softened sampling during label collection, argmax for guidance.

    Parameters
    ----------
    model : nn.Module
        The feedback model Fhat (:class:`services.learner.feedback.FeedbackModel`).
    beta : float
        Inverse temperature of ``softmax(beta * sigmoid(Fhat(s)))`` used when sampling.
    method : str
        The stage-2 method Fhat was trained with: its P(optimal) is a sigmoid per action,
        or a softmax over actions for the categorical methods (the argmax is the same).
    """

    def __init__(self, model: nn.Module, beta: float = 8.0, method: str = "paper") -> None:
        self.model = model
        self.beta = beta
        self.likelihood = get_method(method).likelihood

    def scores(self, obs: np.ndarray) -> np.ndarray:
        """P(action optimal) for every action (``sigmoid(Fhat(s, a))`` for the paper)."""
        with torch.no_grad():
            logits = self.model(torch.as_tensor(np.asarray(obs, dtype=np.float32)))
        return optimality(logits, self.likelihood).numpy()

    def sampling_probs(self, obs: np.ndarray) -> np.ndarray:
        """``softmax(beta * sigmoid(Fhat(s)))``, the label-collection policy."""
        z = self.beta * self.scores(obs)
        z = np.exp(z - z.max(axis=-1, keepdims=True))
        return z / z.sum(axis=-1, keepdims=True)

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> int:
        """Greedy action when ``rng`` is None (guiding RL), else a softened sample; for one
        observation (a batch is refused: ``scores`` and ``sampling_probs`` take one)."""
        if np.ndim(obs) != 1:
            raise ValueError(
                f"act takes one observation (a 1-D array), got shape {np.shape(obs)}; "
                "use scores(batch).argmax(axis=-1) for a batch"
            )
        if rng is None:
            return int(np.argmax(self.scores(obs)))
        probs = self.sampling_probs(obs)
        return int(min(np.searchsorted(np.cumsum(probs), rng.random()), len(probs) - 1))


GREEDY_MEMO_MAX_OBSERVATIONS = 10_000
"""Observations whose greedy action a :class:`GuidingHFPolicy` remembers (~2 MB; emptied
when full)."""


class GuidingHFPolicy(HFPolicy):
    """A pi_HF (:class:`HFPolicy`, or any object with its methods) while it guides RL
    (stage 3), where Fhat no longer learns: the greedy action of each observation is asked
    once and remembered (a guided run meets the same observations again and again: SSSG's
    fixed start, turns on the spot, pi_HF's own path). The same actions as ``policy`` as
    long as its weights do not change."""

    def __init__(self, policy: HFPolicy) -> None:  # no super().__init__: all is the policy's
        self.policy = policy
        self._greedy: dict[bytes, int] = {}

    @property  # type: ignore[override]  # read-only: the policy's
    def model(self) -> nn.Module:
        """The policy's Fhat."""
        return self.policy.model

    def scores(self, obs: np.ndarray) -> np.ndarray:
        """The policy's :meth:`HFPolicy.scores`."""
        return self.policy.scores(obs)

    def sampling_probs(self, obs: np.ndarray) -> np.ndarray:
        """The policy's :meth:`HFPolicy.sampling_probs`."""
        return self.policy.sampling_probs(obs)

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> int:
        """The policy's :meth:`HFPolicy.act`, the greedy action remembered per observation."""
        if rng is not None or np.ndim(obs) != 1:
            return self.policy.act(obs, rng)
        key = np.asarray(obs, dtype=np.float32).tobytes()
        action = self._greedy.get(key)
        if action is None:
            action = self.policy.act(obs)
            if len(self._greedy) >= GREEDY_MEMO_MAX_OBSERVATIONS:
                self._greedy.clear()
            self._greedy[key] = action
        return action


class CollectionRule:
    """The method's rule for the action to execute (and label) while labels are collected.

    Parameters
    ----------
    method : HFMethod
        The stage-2 method; its ``collection`` names the rule.
    policy : HFPolicy
        pi_HF on the learner's Fhat.
    ensemble : FhatEnsemble or None
        The learner's bootstrapped ensemble (``thompson`` and ``info`` need it).
    noise_model : (float, float)
        The (good, bad) per-class label accuracies (``info``'s expected information).
    thompson_period : int
        Collection actions between two Thompson draws of the member to follow.
    revisit_window : int
        ``greedy``: how many last observations count as a loop.
    """

    def __init__(
        self,
        method: HFMethod,
        policy: HFPolicy,
        ensemble: FhatEnsemble | None,
        noise_model: tuple[float, float],
        thompson_period: int,
        revisit_window: int,
    ) -> None:
        if method.uses_ensemble and ensemble is None:
            raise ValueError(f"collection {method.collection!r} needs the ensemble")
        self.method = method
        self.policy = policy
        self.ensemble = ensemble
        self.noise_model = noise_model
        self.thompson_period = thompson_period
        self.n_collection_actions = 0
        self.member = 0
        self.recent_obs: deque[bytes] = deque(maxlen=revisit_window)
        """Observations of the last collection actions (``greedy`` collection's loop test)."""

    def action(self, obs: np.ndarray, rng: np.random.Generator) -> int:
        """The action to execute at ``obs``; draws from ``rng`` only where the rule samples."""
        if self.method.collection == "greedy":
            key = np.asarray(obs, dtype=np.float32).tobytes()
            revisit = key in self.recent_obs
            self.recent_obs.append(key)
            return self.policy.act(obs, rng if revisit else None)
        if self.ensemble is None:
            return self.policy.act(obs, rng)
        if self.n_collection_actions % self.thompson_period == 0:
            self.member = int(rng.integers(self.ensemble.size))
        self.n_collection_actions += 1
        with torch.no_grad():
            logits = self.ensemble(torch.as_tensor(np.asarray(obs, np.float32))[None])[:, 0]
            p_optimal = optimality(logits, self.method.likelihood).numpy()
        if self.method.collection == "thompson":
            return int(np.argmax(p_optimal[self.member]))
        return most_informative_action(p_optimal, *self.noise_model)

    def state_dict(self) -> dict[str, Any]:
        """The rule's own state: the recent observations (``greedy``) or the Thompson
        counter and member (ensemble rules); empty for ``softmax``."""
        if self.method.collection == "greedy":
            n_obs = self.policy.model.normalizer.n_obs
            recent = np.frombuffer(b"".join(self.recent_obs), dtype=np.float32)
            return {"recent_obs": torch.from_numpy(recent.reshape(-1, n_obs).copy())}
        if self.ensemble is not None:
            return {"n_collection_actions": self.n_collection_actions, "member": self.member}
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s keys from ``state`` (extra keys are ignored)."""
        if self.method.collection == "greedy":
            self.recent_obs.clear()
            self.recent_obs.extend(row.tobytes() for row in state["recent_obs"].numpy())
        elif self.ensemble is not None:
            self.n_collection_actions = int(state["n_collection_actions"])
            self.member = int(state["member"])
