"""Every stream of randomness of a run, from one ``numpy.random.SeedSequence``.

A run's integer ``seed`` is the entropy of one :class:`numpy.random.SeedSequence`; each
stream is one of its spawned children (``SeedSequence(seed).spawn(len(Stream))[stream]``),
so streams are statistically independent of each other and of other seeds' streams.

Integer seeds handed to other code (``env.reset(seed=...)``, ``torch.manual_seed``, the
label-noise generator) carry their stream in the top bits: ``(tag << 60) | 60 random bits``
with ``tag = stream + 1``. The evaluation starts come from a separate fixed stream
(:data:`EVALUATION_ENTROPY`) and are 32-bit, i.e. tag 0. So no training reset, label
collection reset or label-noise seed of any run can ever equal an evaluation start seed, or
a seed of another stream: the ranges are disjoint by construction, not by chance.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

TAG_SHIFT = 60
"""Integer seeds are ``(tag << TAG_SHIFT) | value`` with ``value < 2**TAG_SHIFT``."""
EVALUATION_ENTROPY = 0x0E7A_1DA7_E5EE_D5
"""Entropy of the evaluation-start stream (fixed: the same starts for every run)."""


class Stream(IntEnum):
    """The independent streams of one run, in spawn order (never reorder: runs depend on it)."""

    TORCH_INIT = 0
    """Initial weights of pi_RL (actor and critic)."""
    ACTIONS = 1
    """PPO's generator: action sampling, the per-episode eps_HF draw, minibatch order."""
    TRAINING_RESETS = 2
    """Reset seed of every training episode."""
    LABEL_NOISE = 3
    """The simulated feedback's flips (noisy oracle at accuracy C)."""
    LABEL_COLLECTION = 4
    """Stage 2: Fhat's initialisation, pi_HF's sampling, the validation split, first reset."""
    HF_PROBE = 5
    """Action sampling of pi_HF when it is measured alone (``bgrl hf-sweep``)."""


def _tagged(stream: Stream, values: np.ndarray) -> np.ndarray:
    return (np.int64(int(stream) + 1) << np.int64(TAG_SHIFT)) | values.astype(np.int64)


def stream_of(seed: int) -> Stream | None:
    """The stream an integer seed was drawn from; None for an evaluation start (tag 0)."""
    tag = int(seed) >> TAG_SHIFT
    return None if tag == 0 else Stream(tag - 1)


def evaluation_reset_seeds(n: int) -> tuple[int, ...]:
    """The first ``n`` evaluation-start reset seeds (32-bit, the same for every run)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    words = np.random.SeedSequence(EVALUATION_ENTROPY).generate_state(n, np.uint32)
    return tuple(int(w) for w in words)


@dataclass(frozen=True)
class RunSeeds:
    """The streams of the run with integer ``seed`` (see the module docstring)."""

    seed: int

    def __post_init__(self) -> None:
        if not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")

    def sequence(self, stream: Stream) -> np.random.SeedSequence:
        """The stream's SeedSequence: child ``stream`` of ``SeedSequence(seed)``."""
        return np.random.SeedSequence(int(self.seed)).spawn(len(Stream))[int(stream)]

    def generator(self, stream: Stream) -> np.random.Generator:
        """A fresh numpy Generator on the stream."""
        return np.random.default_rng(self.sequence(stream))

    def int_seed(self, stream: Stream) -> int:
        """One tagged integer seed of the stream (for code that takes an int seed)."""
        value = self.sequence(stream).generate_state(1, np.uint64)[0] >> np.uint64(64 - TAG_SHIFT)
        return int(_tagged(stream, np.array([value]))[0])

    def training_resets(self) -> TrainingResets:
        """The reset seeds of the training episodes, drawn in order."""
        return TrainingResets(self.generator(Stream.TRAINING_RESETS))


class TrainingResets:
    """Reset seed of each training episode, drawn in order from the run's stream.

    ``next()`` gives episode 0's seed, then episode 1's...; :meth:`take` draws the same
    values in one call. ``state`` is what a checkpoint stores to resume the sequence.
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng

    def next(self) -> int:
        """The next episode's reset seed."""
        return int(self.take(1)[0])

    def take(self, n: int) -> np.ndarray:
        """The next ``n`` reset seeds (int64)."""
        return _tagged(Stream.TRAINING_RESETS, self.rng.integers(0, 1 << TAG_SHIFT, size=n))

    @property
    def state(self) -> dict:
        """The generator's state (JSON-able)."""
        return self.rng.bit_generator.state

    @state.setter
    def state(self, value: dict) -> None:
        self.rng.bit_generator.state = value
