"""Where stage 2's labels come from: the :class:`FeedbackSource` protocol and its sources.

The noisy Dijkstra oracle (:class:`OracleFeedbackSource`, simulation), decoded EEG feedback
from a queue or callable (:class:`StreamFeedbackSource`) and stored labels
(:class:`ReplayFeedbackSource`); :func:`services.learner.feedback.collect_feedback` takes any.
A source answers a bool (a hard label) or a :class:`DecodedLabel` (the hard label and the
decoder's calibrated evidence, which the ``soft`` label channel reads); the end-to-end
source of the virtual subject and its decoder lives outside the learner
(``services.cli.e2e_feedback``), which must not import the EEG pipeline.
"""

from __future__ import annotations

import math
import queue
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from services.learner.feedback_buffer import FeedbackRecord


@dataclass(frozen=True)
class DecodedLabel:
    """A decoded epoch's feedback: the hard decision and the evidence it was taken from."""

    correct: bool
    """The thresholded decision (P(error) < 0.5): the hard label."""
    log_likelihood_ratio: float
    """``log P(epoch | error) / P(epoch | correct)`` from the decoder's calibrated posterior:
    the soft label (> 0 speaks for an error)."""

    def __post_init__(self) -> None:
        if not math.isfinite(self.log_likelihood_ratio):
            raise ValueError(
                f"log_likelihood_ratio must be finite, got {self.log_likelihood_ratio}"
            )


Label = bool | DecodedLabel
"""What a source answers for a labelled step."""


def unpack_label(label: Label) -> tuple[bool, float | None]:
    """(hard label, log-likelihood ratio or None for a label without evidence)."""
    if isinstance(label, DecodedLabel):
        return label.correct, label.log_likelihood_ratio
    return bool(label), None


@runtime_checkable
class FeedbackSource(Protocol):
    """Anything that judges the action just taken.

    ``feedback(obs, action, optimal)`` returns True (correct), False (error), a
    :class:`DecodedLabel` (a decoder's decision with its likelihood ratio) or None (no label
    for this step, e.g. a rejected EEG epoch). ``optimal`` is the oracle's truth when the
    caller knows it (simulation), else None.
    """

    def feedback(self, obs: np.ndarray, action: int, optimal: bool | None) -> Label | None: ...


@runtime_checkable
class DecodedFeedbackSource(FeedbackSource, Protocol):
    """A source whose labels a decoder makes (the virtual subject end to end): what a run
    records of it and the hard channel's label-noise model."""

    @property
    def decoder_accuracy(self) -> float:
        """The decoder's held-out hard accuracy."""
        ...

    @property
    def subject_quality(self) -> float:
        """The (virtual) subject's quality behind it."""
        ...

    @property
    def noise_model(self) -> tuple[float, float]:
        """(P(decoded correct | correct), P(decoded error | error)) on held-out epochs."""
        ...


class FeedbackSourceFactory(Protocol):
    """Makes the decoded feedback source of run seed ``seed`` whose decoder reaches the
    target held-out accuracy ``decoder_accuracy`` (picklable: spawned workers call it).
    ``services.worker.e2e_feedback.VirtualSubjectFactory`` is one."""

    def __call__(self, seed: int, decoder_accuracy: float) -> DecodedFeedbackSource: ...

    def describe(self) -> dict[str, Any]:
        """The settings its sources are made with (the virtual subject's decoders and
        training passes): a study records them, and a folder holds runs of one."""
        ...

    def describe_defaults(self) -> dict[str, Any]:
        """:meth:`describe` of a factory with the default settings: what the runs of a
        folder that recorded none were made with (folders written before the record)."""
        ...


FEEDBACK_SOURCE = "feedback_source"
"""Key of the settings block of a folder's results (``results.json["config"]``,
``hf_policies.json["config"]``, ``nstar_rows.json["config"]``) holding the settings of its
virtual subjects (:meth:`FeedbackSourceFactory.describe`: their decoders and training passes)."""


def recorded_feedback_source(
    recorded: dict[str, Any] | None,
    stored: Iterable[str | None],
    defaults: Callable[[], dict[str, Any]],
) -> dict[str, Any] | None:
    """The feedback-source settings a folder's runs (or rows) were made with: its record
    ``recorded``; for a folder that holds virtual-subject runs (``stored``: their feedbacks,
    None meaning the oracle's) but recorded nothing, written before the record, ``defaults()``
    (:meth:`FeedbackSourceFactory.describe_defaults`)."""
    if recorded is None and any(feedback not in (None, "oracle") for feedback in stored):
        return defaults()
    return recorded


def one_feedback_source(
    folder: str | Path,
    recorded: dict[str, Any] | None,
    stored: Iterable[str | None],
    given: Iterable[str],
    factory: FeedbackSourceFactory | None,
) -> dict[str, Any] | None:
    """The feedback-source settings ``folder`` records after a call running runs of the
    feedbacks ``given`` with ``factory``: the factory's if they include virtual-subject runs,
    else ``recorded`` (the folder's record, None if none) as it is. ``stored`` are the
    feedbacks of the runs (or rows) the folder holds (None: made before other feedback, the
    oracle's); a folder holding virtual-subject runs that recorded nothing was written before
    the record, with the default settings (:meth:`FeedbackSourceFactory.describe_defaults`).

    A folder holds one set: a ValueError naming the setting (e.g. the decoders) and the
    folder if its virtual-subject runs were made with others, as its groups, tables and
    resume keys would mix the two."""
    if factory is None or all(feedback == "oracle" for feedback in given):
        return recorded
    settings = factory.describe()
    recorded = recorded_feedback_source(recorded, stored, factory.describe_defaults)
    for name in sorted({*(recorded or {}), *settings}):
        if recorded is not None and recorded.get(name) != settings.get(name):
            raise ValueError(
                f"{folder} holds virtual-subject runs made with {name} {recorded.get(name)!r}, "
                f"not {settings.get(name)!r}: a folder holds one set (--decoders); use another "
                "output folder"
            )
    return settings


class OracleFeedbackSource:
    """Simulated feedback: the Dijkstra oracle's judgement flipped at the given accuracy.

    Parameters
    ----------
    accuracy : float, optional
        Probability C that the feedback matches the truth, for good and bad actions alike.
    good_accuracy, bad_accuracy : float, optional
        Separate accuracies for optimal and sub-optimal actions (instead of ``accuracy``).
    seed : int, optional
        Seed of the label noise.
    """

    def __init__(
        self,
        accuracy: float | None = None,
        *,
        good_accuracy: float | None = None,
        bad_accuracy: float | None = None,
        seed: int | None = None,
    ) -> None:
        from services.sim.oracle import NoisyOracleFeedback

        self.noisy = NoisyOracleFeedback(
            accuracy, good_accuracy=good_accuracy, bad_accuracy=bad_accuracy, seed=seed
        )

    def feedback(self, obs: np.ndarray, action: int, optimal: bool | None) -> bool:
        """Noisy version of ``optimal`` (which must be known)."""
        if optimal is None:
            raise ValueError("OracleFeedbackSource needs the oracle's truth (optimal=None given)")
        return bool(self.noisy.feedback(optimal))


class StreamFeedbackSource:
    """Decoded EEG feedback arriving from a live pipeline.

    Parameters
    ----------
    stream : queue.Queue or callable
        A queue of ``bool`` feedback items, or a callable ``get(timeout_s) -> bool | None``.
    timeout_s : float
        How long to wait for the decision of the current action; a missing decision yields
        None (the step gets no label). Default 1.5 s, one action period.
    """

    def __init__(
        self,
        stream: queue.Queue[bool] | Callable[[float], bool | None],
        timeout_s: float = 1.5,
    ) -> None:
        if timeout_s <= 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.stream = stream
        self.timeout_s = timeout_s

    def feedback(self, obs: np.ndarray, action: int, optimal: bool | None) -> bool | None:
        """The next decoded decision, or None if none arrives in time."""
        if isinstance(self.stream, queue.Queue):
            try:
                item = self.stream.get(timeout=self.timeout_s)
            except queue.Empty:
                return None
        else:
            item = self.stream(self.timeout_s)
        return None if item is None else bool(item)


class ReplayFeedbackSource:
    """Stored labels replayed in order (reproduces a recorded session in a seeded env)."""

    def __init__(self, labels: Iterable[Label | None]) -> None:
        self.labels = list(labels)
        self.position = 0

    @classmethod
    def from_records(cls, records: Sequence[FeedbackRecord]) -> ReplayFeedbackSource:
        """Replay the labels of a previous session's records (with their likelihood ratio
        where they had one)."""
        return cls(
            r.label
            if r.log_likelihood_ratio is None
            else DecodedLabel(r.label, r.log_likelihood_ratio)
            for r in records
        )

    def feedback(self, obs: np.ndarray, action: int, optimal: bool | None) -> Label | None:
        """The next stored label; raises when the recording is exhausted."""
        if self.position >= len(self.labels):
            raise IndexError(f"all {len(self.labels)} stored labels have been replayed")
        label = self.labels[self.position]
        self.position += 1
        if label is None or isinstance(label, DecodedLabel):
            return label
        return bool(label)
