"""A smoothness prior for stage 2: each label is evidence about the optimal action of nearby states.

At C = 0.6 one label carries at most ``1 - H(0.6)`` = 0.029 bits (docs/stage2.md), so 1000
labels hardly pin down the optimal action of each state on the way to the goal independently.
Nearby states mostly share their optimal action (the path is mostly "forward"), so a label
on one state is also, weaker, evidence about its neighbours. :class:`KernelEvidence` keeps,
for every training label's state ``s_i``, the kernel-weighted categorical log-likelihood of
every optimal action ``k`` given all training labels ``(s_j, a_j, f_j)``:

    E[i, k] = sum_j w(s_i, s_j) log P(f_j | a_j, optimal = k),
    w(s, s') = exp(-mean_d (x_d - x'_d)^2 / (2 h^2)),

``x`` the observation as Fhat sees it (the fixed normalisation onto [-1, 1]) and ``h`` the
bandwidth. ``P(f | a, k)`` is the categorical method's noisy-label likelihood: g / 1 - g when
``a = k``, 1 - b / b otherwise. ``softmax(E[i])`` is the posterior of the optimal action at
``s_i`` (Nadaraya-Watson weighting of the evidence; Fhat's own label counts with weight 1).
A soft label (``soft`` channel) is a "correct" label of per-label accuracy
``r = P(correct | epoch)`` at even odds: ``P(x | a, k)`` is proportional to r when
``a = k`` and to 1 - r otherwise.
The ``categorical_kernel`` method trains Fhat toward it with cross-entropy, so Fhat stays the
13 -> 16 -> 3 MLP and pi_HF its argmax; no label is spent and nothing but the observation
enters. The cost per label is one pass over the stored labels (O(N n_obs)).
"""

from __future__ import annotations

import numpy as np
import torch

from services.core.actions import N_ACTIONS


def label_log_likelihood(action: int, label: bool, good: float, bad: float) -> np.ndarray:
    """``log P(f | a, optimal = k)`` for every k: the categorical noisy-label likelihood."""
    if label:
        same, other = good, 1.0 - bad
    else:
        same, other = 1.0 - good, bad
    values = np.full(N_ACTIONS, np.log(other))
    values[action] = np.log(same)
    return values


class KernelEvidence:
    """Kernel-weighted label evidence about the optimal action at every training label's state.

    Parameters
    ----------
    n_obs : int
        Observation size.
    bandwidth : float
        Kernel bandwidth h in normalised units (per dimension, on [-1, 1]).
    noise_model : (float, float)
        (good, bad) per-class label accuracies.
    capacity : int
        Most labels held (as the replay buffer's).
    """

    def __init__(
        self,
        n_obs: int,
        bandwidth: float,
        noise_model: tuple[float, float],
        capacity: int = 100_000,
    ) -> None:
        if bandwidth <= 0:
            raise ValueError(f"bandwidth must be > 0, got {bandwidth}")
        self.bandwidth = float(bandwidth)
        self.good, self.bad = noise_model
        self.x = np.zeros((capacity, n_obs))
        self.log_likelihood = np.zeros((capacity, N_ACTIONS))
        self.evidence = np.zeros((capacity, N_ACTIONS))
        self.size = 0

    def weights(self, x: np.ndarray) -> np.ndarray:
        """Kernel weight of the normalised observation ``x`` to every stored one, shape (N,)."""
        squared = np.mean((self.x[: self.size] - x) ** 2, axis=1)
        return np.exp(-squared / (2.0 * self.bandwidth**2))

    def add(self, x: np.ndarray, action: int, label: bool, p_correct: float | None = None) -> None:
        """Add one training label at the normalised observation ``x``: its evidence reaches
        every stored state, theirs reaches it. A soft label gives ``p_correct`` (P(correct |
        epoch) at even odds) and is read as a "correct" label of that accuracy."""
        if self.size == len(self.x):
            raise OverflowError(f"kernel evidence is full ({self.size} labels)")
        x = np.asarray(x, dtype=np.float64)
        if p_correct is None:
            own = label_log_likelihood(action, label, self.good, self.bad)
        else:
            own = label_log_likelihood(action, True, p_correct, p_correct)
        w = self.weights(x)
        n = self.size
        self.evidence[:n] += w[:, None] * own
        self.evidence[n] = w @ self.log_likelihood[:n] + own
        self.x[n] = x
        self.log_likelihood[n] = own
        self.size += 1

    def posterior(self, indices: np.ndarray) -> torch.Tensor:
        """``softmax(E[i])`` of the given stored labels, shape (len(indices), n_actions)."""
        return torch.softmax(torch.from_numpy(self.evidence[indices]).float(), dim=-1)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The stored observations, per-label likelihoods and evidence (filled rows only)."""
        n = self.size
        return {
            "x": torch.from_numpy(self.x[:n].copy()),
            "log_likelihood": torch.from_numpy(self.log_likelihood[:n].copy()),
            "evidence": torch.from_numpy(self.evidence[:n].copy()),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the contents with those of :meth:`state_dict`."""
        n = int(state["x"].shape[0])
        if n > len(self.x):
            raise OverflowError(f"{n} labels exceed the capacity {len(self.x)}")
        self.x[:n] = state["x"].numpy()
        self.log_likelihood[:n] = state["log_likelihood"].numpy()
        self.evidence[:n] = state["evidence"].numpy()
        self.size = n
