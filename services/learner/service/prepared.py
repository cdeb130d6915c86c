"""Labels prepared before their feedback is known: both outcomes computed in advance.

A label's feedback is one bit (correct or error); everything else about it (the marker, the
observation, the action, the oracle's truth and the state the next action is taken in) is
known as soon as the action is executed, the better part of a second before the EEG epoch
after it is decoded. ``POST /hf-sessions/{id}/labels/prepare`` then runs Fhat's update
(1 + K_HF steps) and samples pi_HF's next action on two deep copies of the session's learner
and sampling generator, one per feedback value (:func:`prepare`); the label itself only
swaps the matching copy in (:meth:`HFSession.add_forked_label
<services.learner.service.session.HFSession.add_forked_label>`). The updates are the
deterministic ones :meth:`HFSession.add_label
<services.learner.service.session.HFSession.add_label>` would run, on identical copies, so
the session after a prepared label is bit for bit the one after the same label unprepared.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.learner.feedback import FeedbackLearner
from services.learner.feedback_buffer import FeedbackRecord


@dataclass(frozen=True)
class PreparedOutcome:
    """The learner and sampling generator after one feedback value (and the next action)."""

    learner: FeedbackLearner
    rng: np.random.Generator
    fed: FeedbackRecord
    next_action: int | None


@dataclass(frozen=True)
class PreparedLabel:
    """Both outcomes of one label, valid while the session is at operation ``ops``."""

    marker_id: str
    observation: list[float]
    action: int
    oracle_correct: bool | None
    next_observation: list[float] | None
    ops: int
    """The session's operation count the copies were taken at."""
    outcomes: dict[bool, PreparedOutcome]
    """Keyed by the feedback (True: correct)."""

    def matches(
        self,
        marker_id: str,
        observation: list[float],
        action: int,
        oracle_correct: bool | None,
        next_observation: list[float] | None,
        ops: int,
    ) -> bool:
        """True if a label with these fields, sent at operation ``ops``, is the prepared one."""
        return (
            self.ops == ops
            and self.marker_id == marker_id
            and self.action == action
            and self.oracle_correct == oracle_correct
            and self.observation == observation
            and self.next_observation == next_observation
        )


def prepare(
    forks: dict[bool, tuple[FeedbackLearner, np.random.Generator]],
    *,
    marker_id: str,
    observation: list[float],
    action: int,
    oracle_correct: bool | None,
    next_observation: list[float] | None,
    sample_next: bool,
    ops: int,
) -> PreparedLabel:
    """Learn the label with each feedback value on its own fork (from
    :meth:`HFSession.fork <services.learner.service.session.HFSession.fork>`), then sample
    the next action there if ``sample_next``, as the label route does."""
    obs = np.asarray(observation, dtype=np.float32)
    outcomes = {}
    for correct, (learner, rng) in forks.items():
        fed = learner.add(obs, action, correct, oracle_correct)
        next_action = None
        if sample_next and next_observation is not None:
            next_action = learner.collection_action(
                np.asarray(next_observation, dtype=np.float32), rng
            )
        outcomes[correct] = PreparedOutcome(learner, rng, fed, next_action)
    return PreparedLabel(
        marker_id=marker_id,
        observation=observation,
        action=action,
        oracle_correct=oracle_correct,
        next_observation=next_observation,
        ops=ops,
        outcomes=outcomes,
    )
