"""Stage 2's labels in memory: :class:`FeedbackRecord` (one labelled step) and the replay
buffer of Fhat's training labels (:class:`FeedbackReplayBuffer`, "newer is more important")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

NO_SOFT_LABEL = -1.0
"""``p_correct`` of a label without a soft form (a hard label)."""


class FeedbackReplayBuffer:
    """All training labels ``(s, a, f)``; replay minibatches favour the newest labels.

    Rule: with probability ``newest_fraction`` a minibatch is the ``batch_size`` newest labels;
    otherwise it is drawn uniformly (with replacement) from all labels.
    """

    def __init__(self, n_obs: int, capacity: int = 100_000) -> None:
        self.obs = np.zeros((capacity, n_obs), dtype=np.float32)
        self.actions = np.zeros(capacity, dtype=np.int64)
        self.labels = np.zeros(capacity, dtype=np.float32)
        self.p_correct = np.full(capacity, NO_SOFT_LABEL, dtype=np.float32)
        """Soft labels: P(correct | epoch) at even odds, ``sigmoid(-log-likelihood ratio)``
        (:data:`NO_SOFT_LABEL` for a hard label)."""
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(
        self, obs: np.ndarray, action: int, label: bool, p_correct: float = NO_SOFT_LABEL
    ) -> None:
        """Append one label (with its soft form ``p_correct`` on the soft channel)."""
        if self.size == len(self.labels):
            raise OverflowError(f"feedback buffer is full ({self.size} labels)")
        self.obs[self.size] = obs
        self.actions[self.size] = action
        self.labels[self.size] = float(label)
        self.p_correct[self.size] = p_correct
        self.size += 1

    def sample_indices(
        self, rng: np.random.Generator, batch_size: int, newest_fraction: float
    ) -> np.ndarray:
        """Indices of one replay minibatch under the recency rule."""
        if self.size == 0:
            raise ValueError("cannot sample from an empty feedback buffer")
        if rng.random() < newest_fraction:
            return np.arange(max(0, self.size - batch_size), self.size)
        return rng.integers(0, self.size, size=min(batch_size, self.size))

    def tensors(self, indices: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(obs, actions, labels) tensors of the given rows."""
        return (
            torch.from_numpy(self.obs[indices]),
            torch.from_numpy(self.actions[indices]),
            torch.from_numpy(self.labels[indices]),
        )

    def soft_tensor(self, indices: np.ndarray) -> torch.Tensor:
        """The soft labels (``p_correct``) of the given rows."""
        return torch.from_numpy(self.p_correct[indices])

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The stored labels as tensors (only the filled rows), for checkpoints."""
        return {
            "obs": torch.from_numpy(self.obs[: self.size].copy()),
            "actions": torch.from_numpy(self.actions[: self.size].copy()),
            "labels": torch.from_numpy(self.labels[: self.size].copy()),
            "p_correct": torch.from_numpy(self.p_correct[: self.size].copy()),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the contents with those of :meth:`state_dict`."""
        size = int(state["labels"].shape[0])
        if size > len(self.labels):
            raise OverflowError(f"{size} labels exceed the buffer's capacity {len(self.labels)}")
        self.obs[:size] = state["obs"].numpy()
        self.actions[:size] = state["actions"].numpy()
        self.labels[:size] = state["labels"].numpy()
        self.p_correct[:] = NO_SOFT_LABEL  # checkpoints from before soft labels hold none
        if "p_correct" in state:
            self.p_correct[:size] = state["p_correct"].numpy()
        self.size = size


@dataclass
class FeedbackRecord:
    """One labelled step of a feedback session."""

    obs: list[float]
    action: int
    label: bool
    """The feedback received (True = judged correct)."""
    optimal: bool | None
    """The oracle's truth, when known (simulation); None for real EEG feedback."""
    validation: bool
    """Held out for validation (never trained on)."""
    log_likelihood_ratio: float | None = None
    """The decoder's ``log P(epoch | error) / P(epoch | correct)``, when the source gave one
    (kept on either channel, so a session can be replayed through the other)."""
