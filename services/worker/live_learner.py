"""The learner's side of a live run (``live_session`` jobs): the run's HF session in the
learner service, the labels of accepted decisions sent to it (with their label and
model-version rows) and pi_HF's actions.

:class:`~services.worker.live_session.LiveRunner` owns one :class:`LearnerLink` and uses it
in online sessions only. On resume the HF session is found again by the id the run's row
keeps (its state is on the learner's disk); a label the learner has already seen is ignored
by it (the marker id names the run and the step).
"""

from __future__ import annotations

import logging
from typing import Any

from mne_lsl.lsl import local_clock

from services.core.db.base import utcnow
from services.core.db.live import LiveModelVersion
from services.core.db.models import FeedbackLabel
from services.core.live import LiveOptions
from services.worker.live_services import ServiceCallError, ServiceClient
from services.worker.runtime import Runtime

logger = logging.getLogger(__name__)


class LearnerLink:
    """One live run's HF session in the learner service."""

    def __init__(
        self,
        client: ServiceClient,
        runtime: Runtime,
        run_id: int,
        session_id: int,
        options: LiveOptions,
        hf_session_id: str | None,
    ) -> None:
        self.client = client
        self.runtime = runtime
        self.run_id = run_id
        self.session_id = session_id
        self.options = options
        self.hf_session_id = hf_session_id
        """The learner's HF session (None until :meth:`attach` opens one)."""
        self.next_action: tuple[int, int] | None = None
        """pi_HF's next action and the model version that chose it, or None once executed."""
        self.prepared_labels = 0
        """Labels of this attempt whose Fhat update the learner had prepared."""

    def attach(self) -> dict[str, str] | None:
        """Find the run's HF session again (None), or open one and return what the run's row
        keeps of it (``hf_session_id``; ``hf_method`` and ``label_channel``: how the learner
        created it)."""
        if self.hf_session_id is not None:
            self.client.call("GET", f"/hf-sessions/{self.hf_session_id}")
            return None
        body = {
            "task": self.options.task,
            "map": self.options.map,
            "seed": self.options.seed,
            "label_budget": self.options.label_budget,
        }
        if self.options.hf_method is not None:
            body["method"] = self.options.hf_method
        if self.options.label_channel is not None:
            body["fhat"] = {"label_channel": self.options.label_channel}
        created = self.client.call("POST", "/hf-sessions", json=body)
        self.hf_session_id = created["id"]
        return {
            "hf_session_id": created["id"],
            "hf_method": created["method"],
            "label_channel": created["fhat"].get("label_channel", "hard"),
        }

    def next_action_at(self, observation: list[float]) -> tuple[int, int]:
        """pi_HF's next action and its model version: the one the last label's answer
        carried, else asked for at ``observation`` now (and kept until executed)."""
        if self.next_action is None:
            self.next_action = self.act(observation)
        return self.next_action

    def act(self, observation: list[float]) -> tuple[int, int]:
        """pi_HF's action at ``observation`` and the model version that chose it."""
        answer = self.client.call(
            "POST", f"/hf-sessions/{self.hf_session_id}/act", json={"observation": observation}
        )
        return int(answer["action"]), int(answer["model_version"])

    def send_label(
        self,
        step: int,
        observation: list[float],
        action: int,
        oracle_correct: bool | None,
        decision: dict[str, Any],
        next_observation: list[float] | None = None,
    ) -> bool:
        """Label one accepted decision; returns False once the learner's budget is full.

        With ``next_observation`` the learner's answer carries pi_HF's next action (one
        round trip for the update and the action); it is kept in :attr:`next_action`.
        """
        body: dict[str, Any] = {
            "marker_id": f"run{self.run_id}:{step}",
            "observation": observation,
            "action": action,
            "feedback": decision["feedback"],
            "p_error": decision["p_error"],
            "oracle_correct": oracle_correct,
        }
        if decision.get("log_likelihood_ratio") is not None:  # a calibrated classifier's
            body["log_likelihood_ratio"] = decision["log_likelihood_ratio"]
        if next_observation is not None:
            body["next_observation"] = next_observation
        try:
            answer = self.client.call(  # idempotent by marker_id (a repeat: duplicate)
                "POST", f"/hf-sessions/{self.hf_session_id}/labels", json=body, idempotent=True
            )
        except ServiceCallError as exc:
            if exc.status_code == 409:
                return False
            raise
        updated = local_clock()
        self.prepared_labels += bool(answer.get("prepared"))
        next_ready = None
        if answer.get("next_action") is not None:
            self.next_action = (int(answer["next_action"]), int(answer["model_version"]))
            next_ready = updated
        with self.runtime.sessions() as db:
            db.add(
                FeedbackLabel(
                    session_id=self.session_id,
                    step=step,
                    state=observation,
                    action=action,
                    decoded_error=decision["feedback"] == "error",
                    p_error=decision["p_error"],
                    log_likelihood_ratio=decision.get("log_likelihood_ratio"),
                    oracle_error=None if oracle_correct is None else not oracle_correct,
                    decoded_at=utcnow(),
                )
            )
            db.add(
                LiveModelVersion(
                    run_id=self.run_id,
                    session_id=self.session_id,
                    step=step,
                    labels=int(answer["labels"]),
                    model_version=int(answer["model_version"]),
                    metrics=answer.get("metrics") or {},
                    updated_ts=updated,
                    next_ready_ts=next_ready,
                )
            )
            db.commit()
        return not answer.get("done", False)

    def prepare_label(
        self,
        step: int,
        observation: list[float],
        action: int,
        oracle_correct: bool | None,
        next_observation: list[float],
    ) -> None:
        """Have the learner compute this step's label for both feedback values while its
        epoch is recorded (``POST /labels/prepare``), so that the label's answer, and pi_HF's
        next action in it, need no Fhat update. Best effort: one attempt, and a failure is
        logged only (the label then takes the ordinary path)."""
        body = {
            "marker_id": f"run{self.run_id}:{step}",
            "observation": observation,
            "action": action,
            "oracle_correct": oracle_correct,
            "next_observation": next_observation,
        }
        try:
            self.client.call_once(
                "POST", f"/hf-sessions/{self.hf_session_id}/labels/prepare", json=body
            )
        except Exception as exc:  # an optimisation must not stop the session
            logger.warning("run %d step %d: label not prepared (%s)", self.run_id, step, exc)
