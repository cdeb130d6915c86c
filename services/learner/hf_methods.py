"""Stage-2 methods: how Fhat turns noisy labels into P(action optimal), and which action to label.

The paper's Fhat (``paper``) fits binary cross-entropy to the noisy labels of the taken
action (Akinola et al., ICRA 2020, §Human Feedback Policy). The other methods go after the
paper's own future work (more from fewer labels, active learning); see docs/stage2.md.

* **Label-noise model.** A label of an optimal action says "correct" with probability
  ``good_accuracy`` (g), a label of a sub-optimal one says "error" with ``bad_accuracy`` (b):
  the decoder's per-class accuracies (in simulation both are the known C; online, the
  classifier's calibration recalls).
* ``noise_aware``: forward correction (Patrini et al., CVPR 2017). ``sigmoid(Fhat(s)[a])``
  is the *clean* P(a optimal) = p, and the label's likelihood is
  ``P(f = correct) = g p + (1 - b)(1 - p)``; plain BCE on noisy labels pulls p toward 0.5.
* ``categorical``: one optimal action per state, ``q = softmax(Fhat(s))``, with the same
  noisy-label likelihood per executed action (``p = q[a]``). A "wrong" verdict on one action
  moves probability to the others. Where two actions are optimal the mass splits between
  them, so the argmax stays an optimal action.
* ``thompson`` / ``categorical_thompson``: active queries. A bootstrapped ensemble of Fhats
  (same loss, each label weighted 0 or 2 per member) chooses the collection action: one
  member, drawn every ``thompson_period`` actions, is followed greedily (Thompson sampling,
  Osband et al. 2016). The robot goes where some plausible Fhat believes the goal is, so
  labels fall along candidate paths instead of around the start.
* ``categorical_info``: the collection action is the plausible action (mean P(optimal) at
  least half the best) whose label carries the most expected information about which
  ensemble member is right (BALD, Houlsby et al. 2011).
* ``categorical_onpolicy``: labels where the *greedy* pi_HF goes. The collection action is
  pi_HF's argmax (the policy that is evaluated and guides RL), as in DAgger (Ross et al.,
  AISTATS 2011), so labels land on the states along the greedy policy's way to the goal and
  pile up at the first state where it errs, until the categorical evidence there moves its
  argmax; where the robot is back on an observation it saw in the last ``revisit_window``
  collection actions (a loop: the greedy policy of a deterministic env cycles), it samples
  the paper's softmax(beta * P(optimal)) instead, which breaks the loop. Measured in
  docs/stage2.md ("A new method"): no better than ``categorical`` at C = 0.6 or 0.7.
* ``categorical_kernel``: a smoothness prior that costs no labels. Each training label is
  evidence, weighted by a Gaussian kernel of the (normalised) observations, about the optimal
  action of every nearby state; Fhat is fitted (cross-entropy) to the posterior
  ``softmax(sum_j w(s, s_j) log P(f_j | a_j, k))`` at the labelled states instead of to each
  label alone (:mod:`services.learner.kernel_prior`). Collection as ``categorical``.

* ``bayes_query`` / ``bayes_query_flat``: labels spent where they inform (issue #24). An
  exact per-state posterior of the optimal action (summed log-likelihood ratios; a shared
  "mostly forward" prior learned across states without counting a label twice, or a
  uniform one); certain states are crossed without a label, uncertain ones asked with top-two
  Thompson sampling, and a query that leaves the believed path restarts the episode. Fhat
  fits the posterior (:mod:`services.learner.query`).

Every method keeps Fhat a 13 -> 16 -> 3 MLP and pi_HF = argmax_a Fhat(s, a); only the loss,
the score transform and the collection rule change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from services.learner.networks import ObsNormalizer, layer_init

DEFAULT_ASSUMED_ACCURACY = 0.6
"""Per-class accuracy assumed when no label-noise model is given (a typical subject: the
paper's subjects decoded at 0.60-0.67)."""


@dataclass(frozen=True)
class HFMethod:
    """One stage-2 method: the likelihood of a label and the rule that picks labelled actions."""

    name: str
    likelihood: str
    """``bce`` (the paper), ``forward`` (noise-aware sigmoid) or ``categorical``."""
    collection: str
    """``softmax`` (the paper's softmax(beta * P(optimal))), ``thompson``, ``info``,
    ``greedy`` (pi_HF's argmax, softmax on a revisited observation) or ``bayes`` (transit
    where the per-state posterior is certain, top-two Thompson where not:
    :mod:`services.learner.query`)."""
    prior: str = "none"
    """``none``: Fhat fits each label at its own state; ``kernel``: Fhat fits the
    kernel-weighted posterior of nearby labels (:mod:`services.learner.kernel_prior`);
    ``hierarchical`` / ``flat``: Fhat fits the per-state posterior of the ``bayes``
    collection, with a learned shared prior over the optimal action or a uniform one."""

    @property
    def uses_noise_model(self) -> bool:
        """True if the loss needs the label-noise model."""
        return self.likelihood != "bce"

    @property
    def uses_ensemble(self) -> bool:
        """True if collection needs the bootstrapped ensemble."""
        return self.collection in ("thompson", "info")


HF_METHODS: dict[str, HFMethod] = {
    m.name: m
    for m in (
        HFMethod("paper", "bce", "softmax"),
        HFMethod("noise_aware", "forward", "softmax"),
        HFMethod("categorical", "categorical", "softmax"),
        HFMethod("thompson", "bce", "thompson"),
        HFMethod("categorical_thompson", "categorical", "thompson"),
        HFMethod("categorical_info", "categorical", "info"),
        HFMethod("categorical_onpolicy", "categorical", "greedy"),
        HFMethod("categorical_kernel", "categorical", "softmax", prior="kernel"),
        HFMethod("bayes_query", "categorical", "bayes", prior="hierarchical"),
        HFMethod("bayes_query_flat", "categorical", "bayes", prior="flat"),
    )
}
PAPER_METHOD = "paper"
RECOMMENDED_METHOD = "categorical_kernel"
"""The platform's stage-2 method (``bgrl reproduce --preset platform``, online sessions and
guided-PPO jobs); measured in docs/stage2.md."""


def get_method(name: str) -> HFMethod:
    """The method called ``name``; a ValueError naming the known ones otherwise."""
    try:
        return HF_METHODS[name]
    except KeyError:
        raise ValueError(
            f"unknown stage-2 method {name!r}; expected one of {sorted(HF_METHODS)}"
        ) from None


def optimality(logits: torch.Tensor, likelihood: str) -> torch.Tensor:
    """P(action optimal) from Fhat's logits: sigmoid, or softmax for the categorical model."""
    if likelihood == "categorical":
        return torch.softmax(logits, dim=-1)
    return torch.sigmoid(logits)


def p_judged_correct(
    p_optimal: torch.Tensor, good: float | torch.Tensor, bad: float | torch.Tensor
) -> torch.Tensor:
    """P(label says correct) = g p + (1 - b)(1 - p): the label-noise model applied to p
    (g and b may be per-label tensors: a soft label is a "correct" one with g = b = r)."""
    return good * p_optimal + (1.0 - bad) * (1.0 - p_optimal)


def label_nll(
    logits: torch.Tensor,
    actions: torch.Tensor,
    labels: torch.Tensor,
    likelihood: str,
    good: float | torch.Tensor,
    bad: float | torch.Tensor,
) -> torch.Tensor:
    """Negative log-likelihood of each label, shape ``logits.shape[:-1]``.

    ``logits`` is (..., N, n_actions) (a leading ensemble axis is allowed), ``actions`` and
    ``labels`` are (N,).
    """
    index = actions.long().expand(logits.shape[:-1]).unsqueeze(-1)
    labels = labels.float().expand(logits.shape[:-1])
    if likelihood == "bce":
        taken = logits.gather(-1, index).squeeze(-1)
        return nn.functional.binary_cross_entropy_with_logits(taken, labels, reduction="none")
    p_optimal = optimality(logits, likelihood).gather(-1, index).squeeze(-1)
    p_correct = p_judged_correct(p_optimal, good, bad).clamp(1e-6, 1 - 1e-6)
    return -(labels * torch.log(p_correct) + (1 - labels) * torch.log1p(-p_correct))


def mean_label_loss(
    logits: torch.Tensor,
    actions: torch.Tensor,
    labels: torch.Tensor,
    likelihood: str,
    good: float | torch.Tensor,
    bad: float | torch.Tensor,
) -> torch.Tensor:
    """Mean of :func:`label_nll` over the labels (for ``bce`` exactly the paper's BCE loss,
    ``binary_cross_entropy_with_logits`` with its mean reduction, bit for bit)."""
    if likelihood == "bce":
        taken = logits.gather(-1, actions.long().unsqueeze(-1)).squeeze(-1)
        return nn.functional.binary_cross_entropy_with_logits(taken, labels.float())
    return label_nll(logits, actions, labels, likelihood, good, bad).mean()


class FhatEnsemble(nn.Module):
    """K Fhats (each 13 -> 16 tanh -> 3) evaluated in one batched pass: (N, 13) -> (K, N, 3)."""

    def __init__(self, normalizer: ObsNormalizer, size: int, hidden_size: int, n_actions: int):
        super().__init__()
        self.normalizer = normalizer
        hidden = [layer_init(nn.Linear(normalizer.n_obs, hidden_size)) for _ in range(size)]
        output = [layer_init(nn.Linear(hidden_size, n_actions), std=1.0) for _ in range(size)]
        self.w1 = nn.Parameter(torch.stack([h.weight.data.T for h in hidden]))
        self.b1 = nn.Parameter(torch.stack([h.bias.data for h in hidden]))
        self.w2 = nn.Parameter(torch.stack([o.weight.data.T for o in output]))
        self.b2 = nn.Parameter(torch.stack([o.bias.data for o in output]))

    @property
    def size(self) -> int:
        """Number of members K."""
        return int(self.w1.shape[0])

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Logits of every member, shape (K, N, n_actions)."""
        x = self.normalizer(obs)
        hidden = torch.tanh(torch.einsum("ni,kih->knh", x, self.w1) + self.b1[:, None])
        return torch.einsum("knh,kha->kna", hidden, self.w2) + self.b2[:, None]


def expected_information(p_correct: np.ndarray) -> np.ndarray:
    """BALD score per action: I(label; member) = H(mean_k p) - mean_k H(p_k).

    ``p_correct`` is (K, n_actions): each member's P(label says correct) for each action.
    """

    def entropy(p: np.ndarray) -> np.ndarray:
        p = np.clip(p, 1e-12, 1 - 1e-12)
        return -(p * np.log(p) + (1 - p) * np.log(1 - p))

    return entropy(p_correct.mean(axis=0)) - entropy(p_correct).mean(axis=0)


def most_informative_action(p_optimal: np.ndarray, good: float, bad: float) -> int:
    """The plausible action whose label tells most about the ensemble (``categorical_info``).

    ``p_optimal`` is (K, n_actions). Plausible: mean P(optimal) at least half the best mean,
    so the query stays on a path some member believes in.
    """
    mean = p_optimal.mean(axis=0)
    scores = expected_information(good * p_optimal + (1 - bad) * (1 - p_optimal))
    scores = np.where(mean >= 0.5 * mean.max(), scores, -np.inf)
    return int(np.argmax(scores))
