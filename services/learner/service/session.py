"""One online HF-training session: Fhat, its replay buffer and pi_HF, label by label.

A session is stage 2 of ``bgrl reproduce`` (:func:`services.learner.feedback.collect_feedback`)
with the environment loop outside: the caller asks for an action (:meth:`HFSession.act`),
executes it, and sends the decoded feedback back (:meth:`HFSession.add_label`). With the same
``seed`` and the same labels it trains exactly the Fhat that ``collect_feedback`` trains:

* Fhat's initial weights, the 20 % validation hold-out and the replay minibatches come from
  :class:`~services.learner.feedback.FeedbackLearner` seeded with the run's
  ``LABEL_COLLECTION`` stream (:mod:`services.learner.seeding`), as in ``bgrl reproduce``;
* every training label is one SGD step plus K_HF replay steps
  (:meth:`FeedbackLearner.add <services.learner.feedback.FeedbackLearner.add>`);
* pi_HF samples ``softmax(beta * sigmoid(Fhat(s)))`` from
  :func:`~services.learner.feedback.sampling_rng`, one draw per sampled action.

:meth:`HFSession.state_dict` holds everything the next label depends on, so a session
restored from it continues bit for bit. :meth:`HFSession.fork` copies the learner so that a
label's update can be computed before its feedback is known
(:mod:`services.learner.service.prepared`).
"""

from __future__ import annotations

import copy
import math
import threading
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from services.learner.feedback import (
    FeedbackConfig,
    FeedbackLearner,
    sampling_rng,
)
from services.learner.feedback_buffer import FeedbackRecord
from services.learner.networks import ObsNormalizer
from services.learner.seeding import RunSeeds, Stream
from services.learner.service.errors import (
    InvalidRequestError,
    LabelBudgetError,
    MarkerConflictError,
)
from services.learner.service.labels import LabelRecord, LabelTable
from services.sim.env import N_RAYS, RAY_LENGTH_M
from services.sim.maps import NavMap, load_map

STATE_FORMAT = 2
"""Version of :meth:`HFSession.state_dict`'s layout (1: before :attr:`HFSession.ops`)."""
OBSERVATION_TOLERANCE = 1e-4
"""How far (in the observation's units) a value may lie outside the env's observation space
and still be accepted (rounding by the client)."""


def observation_space(nav_map: NavMap) -> spaces.Box:
    """The BrainNav env's observation space on ``nav_map`` (13 rays/goal/heading bounds)."""
    high = np.array([RAY_LENGTH_M] * N_RAYS + [nav_map.diagonal, math.pi, math.pi], np.float32)
    low = np.array([0.0] * N_RAYS + [0.0, -math.pi, -math.pi], dtype=np.float32)
    return spaces.Box(low=low, high=high, dtype=np.float32)


@dataclass(frozen=True)
class SessionSpec:
    """What a session was created with (kept in ``session.json``)."""

    id: str
    task: str
    map: str
    """Name of the map (file stem)."""
    map_path: str
    seed: int
    label_budget: int
    method: str
    fhat: dict[str, Any]
    """The :class:`FeedbackConfig` fields."""
    created_at: datetime

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {**asdict(self), "created_at": self.created_at.isoformat()}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> SessionSpec:
        """Rebuild from :meth:`to_json`."""
        return cls(**{**data, "created_at": datetime.fromisoformat(data["created_at"])})

    @property
    def learner_seed(self) -> int:
        """The integer seed of stage 2 for run seed ``seed`` (as ``bgrl reproduce``)."""
        return RunSeeds(self.seed).int_seed(Stream.LABEL_COLLECTION)


@dataclass(frozen=True)
class LabelOutcome:
    """What :meth:`HFSession.add_label` did."""

    record: LabelRecord
    duplicate: bool
    """The marker id had been labelled before; nothing changed."""
    prepared: bool = False
    """The update had been computed in advance (:mod:`services.learner.service.prepared`)."""


class HFSession:
    """Fhat, its buffer and pi_HF of one session; callers hold :attr:`lock` around each use."""

    def __init__(self, spec: SessionSpec) -> None:
        self.spec = spec
        self.config = FeedbackConfig(**spec.fhat)
        space = observation_space(load_map(Path(spec.map_path)))
        self._obs_low = space.low.astype(np.float64) - OBSERVATION_TOLERANCE
        self._obs_high = space.high.astype(np.float64) + OBSERVATION_TOLERANCE
        normalizer = ObsNormalizer.from_space(space)
        self.learner = FeedbackLearner(normalizer, self.config, spec.learner_seed)
        self.policy = self.learner.policy
        self.rng = sampling_rng(spec.learner_seed)
        self.labels = LabelTable(spec.label_budget, normalizer.n_obs)
        self.ops = 0
        """Operations that changed the state: new labels and sampled actions (the journal's
        sequence numbers, :mod:`services.learner.service.journal`)."""
        self.lock = threading.Lock()

    @property
    def id(self) -> str:
        return self.spec.id

    @property
    def model_version(self) -> int:
        """Training labels Fhat has been updated with (changes exactly when Fhat does)."""
        return len(self.learner.buffer)

    @property
    def done(self) -> bool:
        """True once the label budget is reached."""
        return len(self.labels) >= self.spec.label_budget

    def check_observation(self, observation: list[float], field: str = "observation") -> None:
        """Raise :class:`InvalidRequestError` naming ``field.<i>`` unless every value lies in
        the env's observation space on the session's map.

        The env never leaves it; a value far outside (e.g. ``1e39``, which is infinite as the
        float32 Fhat computes in) would turn Fhat's weights into NaN for good.
        """
        values = np.asarray(observation, dtype=np.float64)
        if values.shape != self._obs_low.shape:
            raise InvalidRequestError(
                f"{field} must hold {self._obs_low.size} numbers, got shape {values.shape}",
                field=field,
            )
        outside = ~((values >= self._obs_low) & (values <= self._obs_high))
        if outside.any():
            i = int(np.argmax(outside))
            low = self._obs_low[i] + OBSERVATION_TOLERANCE
            high = self._obs_high[i] - OBSERVATION_TOLERANCE
            raise InvalidRequestError(
                f"{field}.{i} is {values[i]:g}, outside the env's range [{low:.6g}, {high:.6g}] "
                f"on map {self.spec.map!r}: not an observation of this task",
                field=f"{field}.{i}",
            )

    def act(self, observation: list[float], greedy: bool) -> int:
        """pi_HF's action: a sample (label collection) or the greedy argmax (guidance)."""
        obs = np.asarray(observation, dtype=np.float32)
        if greedy:
            return self.policy.act(obs)
        self.ops += 1
        return self.learner.collection_action(obs, self.rng)

    def add_label(
        self,
        marker_id: str,
        observation: list[float],
        action: int,
        correct: bool,
        p_error: float | None = None,
        oracle_correct: bool | None = None,
        log_likelihood_ratio: float | None = None,
    ) -> LabelOutcome:
        """Store the label and update Fhat (1 + K_HF steps unless it is held out).

        A marker id labelled before changes nothing (``duplicate``) if it carries the same
        label, and raises :class:`MarkerConflictError` if not; a new label once the budget is
        reached raises :class:`LabelBudgetError`; a session on the soft channel refuses a
        label without ``log_likelihood_ratio`` (:class:`InvalidRequestError`).
        """
        obs = np.asarray(observation, dtype=np.float32)
        known = self.check_label(
            marker_id, obs, action, correct, p_error, oracle_correct, log_likelihood_ratio
        )
        if known is not None:
            return known
        fed = self.learner.add(obs, action, correct, oracle_correct, log_likelihood_ratio)
        return self._record(marker_id, fed, p_error, log_likelihood_ratio)

    def check_label(
        self,
        marker_id: str,
        obs: np.ndarray,
        action: int,
        correct: bool,
        p_error: float | None,
        oracle_correct: bool | None,
        log_likelihood_ratio: float | None = None,
    ) -> LabelOutcome | None:
        """The ``duplicate`` outcome of a label sent again, None for a new label that fits
        the budget (raises as :meth:`add_label`)."""
        known = self.labels.get(marker_id)
        if known is not None:
            same = known.observation == obs.tolist() and (
                known.action,
                known.correct,
                known.p_error,
                known.oracle_correct,
                known.log_likelihood_ratio,
            ) == (action, correct, p_error, oracle_correct, log_likelihood_ratio)
            if not same:
                raise MarkerConflictError(
                    f"marker {marker_id!r} was labelled before with a different observation, "
                    "action or feedback",
                    field="marker_id",
                )
            return LabelOutcome(known, duplicate=True)
        if self.done:
            raise LabelBudgetError(
                f"session {self.id} has all {self.spec.label_budget} labels of its budget"
            )
        if self.learner.soft and log_likelihood_ratio is None:
            raise InvalidRequestError(
                f"session {self.id} reads labels on the soft channel: each label needs the "
                "classifier's log_likelihood_ratio",
                field="log_likelihood_ratio",
            )
        return None

    def fork(self) -> tuple[FeedbackLearner, np.random.Generator]:
        """Deep copies of the learner and the sampling generator (caller holds :attr:`lock`):
        a label and an action applied to them leave this session unchanged."""
        return copy.deepcopy((self.learner, self.rng))

    def add_forked_label(
        self,
        marker_id: str,
        learner: FeedbackLearner,
        rng: np.random.Generator,
        fed: FeedbackRecord,
        p_error: float | None,
        sampled: bool,
        log_likelihood_ratio: float | None = None,
    ) -> LabelOutcome:
        """Adopt a :meth:`fork` of this session that learned label ``fed`` (and then sampled
        one action if ``sampled``): afterwards the session is exactly what :meth:`add_label`
        (and :meth:`act`) would have made it. The caller checked the label with
        :meth:`check_label` and that the session did not change since the fork.
        """
        self.learner, self.policy, self.rng = learner, learner.policy, rng
        outcome = self._record(marker_id, fed, p_error, log_likelihood_ratio, prepared=True)
        if sampled:
            self.ops += 1
        return outcome

    def _record(
        self,
        marker_id: str,
        fed: FeedbackRecord,
        p_error: float | None,
        log_likelihood_ratio: float | None,
        prepared: bool = False,
    ) -> LabelOutcome:
        """Enter a label the learner has learned in the label table (a prepared label's
        update is the hard one, so its ratio is given here, not taken from ``fed``)."""
        record = LabelRecord(
            marker_id=marker_id,
            observation=fed.obs,
            action=fed.action,
            correct=fed.label,
            p_error=p_error,
            oracle_correct=fed.optimal,
            validation=fed.validation,
            model_version=self.model_version,
            log_likelihood_ratio=log_likelihood_ratio,
        )
        self.labels.append(record)
        self.ops += 1
        return LabelOutcome(record, duplicate=False, prepared=prepared)

    def metrics(self) -> dict[str, Any]:
        """Label counts, Fhat's validation accuracies and the realised label accuracy."""
        acc_noisy, acc_true = self.learner.validation_accuracy()
        labels = self.labels
        n_validation = len(self.learner.validation)
        return {
            "training_labels": len(labels) - n_validation,
            "validation_labels": n_validation,
            "validation_accuracy": acc_noisy,
            "validation_accuracy_true": acc_true,
            "label_accuracy": labels.n_agree / labels.n_known if labels.n_known else None,
            "fhat_updates": self.learner.n_updates,
        }

    def model_metrics(self) -> dict[str, Any]:
        """What an exported pi_HF records of its training: :meth:`metrics` and the stage-2
        method (``hf_method``)."""
        return {**self.metrics(), "hf_method": self.spec.method}

    def state_dict(self) -> dict[str, Any]:
        """Everything the next label and action depend on (``torch.load(weights_only=True)``)."""
        return {
            "format": STATE_FORMAT,
            "ops": self.ops,
            "learner": self.learner.state_dict(),
            "sampling_rng": self.rng.bit_generator.state,
            "labels": self.labels.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s state (format 1, written before the journal, counts
        no operations)."""
        if state.get("format") not in (1, STATE_FORMAT):
            raise ValueError(f"unknown session state format {state.get('format')!r}")
        self.ops = int(state.get("ops", 0))
        self.learner.load_state_dict(state["learner"])
        self.rng.bit_generator.state = state["sampling_rng"]
        self.labels.load_state_dict(state["labels"])
