"""``live_session`` jobs: a lab session's calibration, test or online loop across the sim,
EEG and learner services (issue 10).

Each step: the action (random for calibration and test, pi_HF's from the learner online) is
executed by the sim (``POST /sessions/{id}/step``, which publishes its LSL marker carrying
the oracle's label); the marker row is written; test and online sessions then ask the EEG
service for the decision on the [0, 0.8] s epoch after it (decision row: accepted, or
rejected and why); online, an accepted decision goes to the learner as a label (label row)
and its answer carries pi_HF's next action from the updated model (model-version row). A
calibration binds no classifier: the EEG service records the stream and every marker (its
live recording, named after the run) and stores the recording when the session ends. Paced
sessions keep one action every ``period_s`` on the runner's clock; accelerated ones run as
fast as the services answer while the virtual subject's clock advances ``period_s`` per
action.

Resume: every attempt starts from the rows. The marker whose decision was not written is
the label in flight: it is recorded as rejected ("lost") and the loop goes on with the next
step; a decision whose label was not written is sent again (the learner ignores a marker id
it has seen). A calibration whose recording the EEG service already stored goes straight to
the finish, which completes what the last attempt left undone (``live_finish``). A service
that restarts is waited for (backoff) and re-attached: a sim session that is gone is opened
again (new episode), the HF session is found again (its state is on the learner's disk),
the EEG source re-connects.

The learner's side (the HF session, the labels, pi_HF's actions) is ``live_learner``'s
:class:`~services.worker.live_learner.LearnerLink`; the end of a run is ``live_finish``.
"""

from __future__ import annotations

import logging
import time
from datetime import UTC, datetime
from typing import Any

import httpx
import numpy as np
from mne_lsl.lsl import local_clock
from pydantic import ValidationError
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.core.db.base import utcnow
from services.core.db.live import LiveDecision, LiveMarker, LiveRun, end_live_run
from services.core.db.models import Classifier, FeedbackLabel, LabSession, Rig
from services.core.feedback import LabelChannel
from services.core.live import (
    DEFAULT_ACTIONS,
    ONLINE_ACTIONS_PER_LABEL,
    LiveOptions,
    default_label_channel,
    has_calibrated_posterior,
)
from services.core.markers import ActionMarker
from services.core.settings import load_settings
from services.worker.live_eeg import EegDecoder, install_classifier
from services.worker.live_finish import RunFinish
from services.worker.live_learner import LearnerLink
from services.worker.live_services import (
    LiveSettings,
    ServiceCallError,
    ServiceDownError,
    clients,
)
from services.worker.runtime import JobConfigError, JobContext, JobOutcome

logger = logging.getLogger(__name__)

PROGRESS_EVERY_S = 1.0


def _options(context: JobContext) -> tuple[int, LiveOptions]:
    config = dict(context.config)
    run_id = config.pop("run_id", None)
    config.pop("session_id", None)
    if not isinstance(run_id, int):
        raise JobConfigError("run_id: a live_session job needs the id of its live run")
    try:
        return run_id, LiveOptions.model_validate(config)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise JobConfigError(f"{'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def online_label_channel(db: Session, run: LiveRun) -> LabelChannel:
    """The channel of an online run that asked for none: the one its learner session was
    opened with, once it was (a resumed run keeps it), else the default for its classifier
    (soft if the classifier has a calibrated posterior)."""
    if run.hf_session_id is not None:
        return "soft" if run.label_channel == "soft" else "hard"  # None: opened as hard
    classifier_id = (run.options or {}).get("classifier_id")
    classifier = db.get(Classifier, classifier_id) if isinstance(classifier_id, int) else None
    calibrated = classifier is not None and has_calibrated_posterior(classifier.metrics)
    return default_label_channel(calibrated)


class LiveRunner:
    """Runs one live run from where its rows stop."""

    def __init__(self, context: JobContext, run_id: int, options: LiveOptions) -> None:
        self.context = context
        self.runtime = context.runtime
        self.settings = load_settings(LiveSettings)
        self.options = options
        self.services = clients(self.settings, on_retry=context.check_stop)
        with self.runtime.sessions() as db:
            run = db.get(LiveRun, run_id)
            if run is None:
                raise JobConfigError(f"run_id: no live run {run_id}")
            lab = db.get(LabSession, run.session_id)
            assert lab is not None
            self.run_id, self.session_id, self.mode = run.id, run.session_id, run.mode
            self.subject_id = lab.subject_id
            # the rig's channel map, for the EEG service reading its LSL stream
            rig = db.get(Rig, lab.rig_id) if lab.rig_id is not None else None
            self.channel_map = rig.channel_map if rig is not None else None
            self.sim_session_id = run.sim_session_id
            if run.mode == "online" and options.label_channel is None:
                channel = online_label_channel(db, run)
                options = self.options = options.model_copy(update={"label_channel": channel})
            self.learner = LearnerLink(
                self.services["learner"],
                self.runtime,
                run_id=run.id,
                session_id=run.session_id,
                options=options,
                hf_session_id=run.hf_session_id,
            )
            self.done = db.scalar(select(func.count()).where(LiveMarker.run_id == run_id)) or 0
            if self.done:
                run.resumes += 1
            run.status, run.job_id = "running", context.job_id
            lab.status = "running"
            db.commit()
        if self.mode in ("test", "online") and options.classifier_id is None:
            raise JobConfigError(f"classifier_id is required for a {self.mode} session")
        self.virtual_seed = (
            options.virtual_seed if options.virtual_seed is not None else self.subject_id
        )
        self.observation: list[float] = []
        self.episode_over = False
        self.decoder: EegDecoder | None = None
        self.stored_recording: dict[str, Any] | None = None
        """The EEG service's stored live recording of a calibration (``RecordingPublic``)."""
        self.last_progress = 0.0
        self.finishing = RunFinish(
            context, self.run_id, self.session_id, options, self.services, self._set_run
        )

    # ----------------------------------------------------------------- helpers
    def _set_run(self, **values: Any) -> None:
        with self.runtime.sessions() as db:
            run = db.get(LiveRun, self.run_id)
            assert run is not None
            for key, value in values.items():
                setattr(run, key, value)
            db.commit()

    def _stop_requested(self) -> bool:
        with self.runtime.sessions() as db:
            return bool(db.scalar(select(LiveRun.stop_requested).where(LiveRun.id == self.run_id)))

    def _labels(self) -> int:
        with self.runtime.sessions() as db:
            return (
                db.scalar(select(func.count()).where(FeedbackLabel.session_id == self.session_id))
                or 0
            )

    # ------------------------------------------------------------------ attach
    def attach_sim(self) -> None:
        sim = self.services["sim"]
        if self.sim_session_id is not None:
            try:
                state = sim.call("GET", f"/sessions/{self.sim_session_id}")
                self.observation = list(state["observation"])
                self.episode_over = bool(state["terminated"] or state["truncated"])
                return
            except ServiceCallError as exc:
                if exc.status_code not in (404, 410):
                    raise
                logger.info("sim session %s is gone; opening a new one", self.sim_session_id)
        seed = self.options.seed + 1000 * self.done
        created = sim.call(
            "POST",
            "/sessions",
            json={"task": self.options.task, "map": self.options.map, "seed": seed},
        )
        self.sim_session_id = created["id"]
        self.observation = list(created["observation"])
        self.episode_over = False
        self._set_run(sim_session_id=self.sim_session_id)

    @property
    def recording_name(self) -> str:
        """Name of a calibration's live recording in the EEG service (one per run, so a
        resumed run continues it)."""
        return f"live-run-{self.run_id}-calibration"

    def attach_eeg(self) -> None:
        """Connect the EEG source: bound to the classifier (test, online), or recorded by the
        EEG service's live recording (calibration)."""
        from services.eeg.virtual.source import VirtualEEGSource

        eeg_id = None
        if self.mode != "calibration":
            eeg_id = install_classifier(self.runtime, self.options.classifier_id or 0)
            self._set_run(eeg_classifier_id=eeg_id)
        source = None
        if self.options.eeg_source == "virtual":
            start = 0.0 if self.options.accelerated else local_clock()
            if self.options.accelerated and self.done:
                start = (self._last_eeg_ts() or 0.0) + 1.0
            source = VirtualEEGSource(
                quality=self.options.virtual_quality,
                seed=self.virtual_seed,
                start_timestamp=start,
            )
            source.n_markers = self.done  # the trials' random streams continue
        self.decoder = EegDecoder(
            self.services["eeg"],
            eeg_id,
            source=source,
            accelerated=self.options.accelerated,
            stream_name=self.options.stream_name,
            channel_map=self.channel_map,
            retry_s=self.settings.live_retry_s,
            period_s=self.options.period_s,
            recording=self.recording_name if self.mode == "calibration" else None,
        )
        self.decoder.attach()

    def _last_eeg_ts(self) -> float | None:
        with self.runtime.sessions() as db:
            return db.scalar(
                select(func.max(LiveMarker.eeg_ts)).where(LiveMarker.run_id == self.run_id)
            )

    # ---------------------------------------------------------------- recovery
    def recover_in_flight(self) -> None:
        """Settle the step the last attempt left half done (see the module docstring)."""
        if self.done == 0 or self.mode == "calibration":
            return
        step = self.done - 1
        with self.runtime.sessions() as db:
            marker = db.scalar(
                select(LiveMarker).where(LiveMarker.run_id == self.run_id, LiveMarker.step == step)
            )
            decision = db.scalar(
                select(LiveDecision).where(
                    LiveDecision.run_id == self.run_id, LiveDecision.step == step
                )
            )
            assert marker is not None
            if decision is None:
                db.add(
                    LiveDecision(
                        run_id=self.run_id,
                        session_id=self.session_id,
                        step=step,
                        status="rejected",
                        reason="lost: the session stopped before its epoch was decoded",
                        oracle_correct=marker.oracle_correct,
                        decided_ts=local_clock(),
                    )
                )
                db.commit()
                return
            labelled = db.scalar(
                select(FeedbackLabel.id).where(
                    FeedbackLabel.session_id == self.session_id, FeedbackLabel.step == step
                )
            )
            marker_row = (marker.observation, marker.action, marker.oracle_correct)
            feedback = {"status": decision.status, "feedback": decision.feedback,
                        "p_error": decision.p_error,
                        "log_likelihood_ratio": decision.log_likelihood_ratio}  # fmt: skip
        if self.mode == "online" and decision.status == "ok" and labelled is None:
            self.learner.send_label(step, *marker_row, feedback)

    # -------------------------------------------------------------------- loop
    def choose_action(self, step: int) -> tuple[int, int | None]:
        if self.mode != "online":
            rng = np.random.default_rng([self.options.seed, step])
            return int(rng.integers(3)), None
        return self.learner.next_action_at(self.observation)

    def execute(self, action: int) -> dict[str, Any]:
        """The sim executes ``action``; a sim session lost to a restart is re-opened once."""
        try:
            return self.services["sim"].call(
                "POST", f"/sessions/{self.sim_session_id}/step", json={"action": action}
            )
        except ServiceCallError as exc:
            if exc.status_code not in (404, 410):
                raise
        self.sim_session_id = None
        self.attach_sim()
        return self.services["sim"].call(
            "POST", f"/sessions/{self.sim_session_id}/step", json={"action": action}
        )

    def total_actions(self) -> int:
        if self.options.n_actions is not None:
            return self.options.n_actions
        if self.mode == "online":
            return self.options.label_budget * ONLINE_ACTIONS_PER_LABEL
        return DEFAULT_ACTIONS[self.mode]

    def step(self, step: int) -> bool:
        """Run action ``step``; returns False when the session is complete.

        On the path from the epoch's end to the next action there is one call to the EEG
        service (the decision), one commit (its row, before the label is sent, so a crash
        cannot lose a label the learner has) and one call to the learner (the label's
        answer carries the next action); the sim's episode reset and, online, the label's
        Fhat update for both feedback values (:meth:`LearnerLink.prepare_label`) happen
        while the epoch is still being recorded.
        """
        action, version = self.choose_action(step)
        obs_before = list(self.observation)
        out = self.execute(action)
        marker = ActionMarker.model_validate(out["marker"])
        now_wall, now_clock = time.time(), local_clock()
        if self.decoder is not None:
            eeg_ts = self.decoder.next_eeg_timestamp(marker.timestamp)
        elif self.options.accelerated:  # no EEG source: the virtual clock
            eeg_ts = step * self.options.period_s
        else:
            eeg_ts = marker.timestamp
        with self.runtime.sessions() as db:
            db.add(
                LiveMarker(
                    run_id=self.run_id,
                    session_id=self.session_id,
                    step=step,
                    sim_session_id=marker.session_id,
                    sim_step=marker.step,
                    episode=marker.episode,
                    action=action,
                    oracle_correct=marker.correct,
                    observation=obs_before,
                    policy_version=version,
                    marker_ts=marker.timestamp,
                    eeg_ts=eeg_ts,
                    executed_at=datetime.fromtimestamp(
                        now_wall - (now_clock - marker.timestamp), UTC
                    ),
                )
            )
            db.commit()
        self.learner.next_action = None
        self.observation = list(out["observation"])
        if out["terminated"] or out["truncated"]:
            reset = self.services["sim"].call("POST", f"/sessions/{self.sim_session_id}/reset")
            self.observation = list(reset["observation"])
        self.episode_over = False
        more = True
        if self.mode == "online" and self.decoder is not None:
            self.learner.prepare_label(step, obs_before, action, marker.correct, self.observation)
        if self.decoder is not None:
            decision, epoch_end, decided = self.decoder.decide(
                marker.model_copy(update={"timestamp": eeg_ts})
            )
            if self.mode == "calibration":  # recorded only: no classifier, no decision row
                return more
            with self.runtime.sessions() as db:
                db.add(
                    LiveDecision(
                        run_id=self.run_id,
                        session_id=self.session_id,
                        step=step,
                        status=decision["status"],
                        reason=decision.get("reason"),
                        feedback=decision.get("feedback"),
                        p_error=decision.get("p_error"),
                        log_likelihood_ratio=decision.get("log_likelihood_ratio"),
                        oracle_correct=marker.correct,
                        classifier_id=self.decoder.classifier_id,
                        epoch_end_ts=epoch_end,
                        decided_ts=decided,
                    )
                )
                db.commit()
            if self.mode == "online" and decision["status"] == "ok":
                more = self.learner.send_label(
                    step, obs_before, action, marker.correct, decision, self.observation
                )
        if self.mode == "online" and more:
            self.learner.next_action_at(self.observation)
        return more

    def run(self) -> JobOutcome:
        total = self.total_actions()
        if self.mode == "calibration" and self.done:
            self.stored_recording = self.finishing.stored_calibration_recording(self.recording_name)
        if self.stored_recording is not None:
            # an earlier attempt ended the session and had its recording stored: finish it
            # (recording anew under the run's name would store a second, empty recording)
            return self.finish(self.done < total)
        try:
            self.attach_sim()
            if self.mode == "online" and (opened := self.learner.attach()) is not None:
                self._set_run(**opened)
            self.attach_eeg()
            self.recover_in_flight()
            if self.episode_over:
                reset = self.services["sim"].call("POST", f"/sessions/{self.sim_session_id}/reset")
                self.observation = list(reset["observation"])
            origin, first = local_clock(), self.done
            stopped = False
            step = self.done
            while step < total:
                self.context.check_stop()
                if self._stop_requested():
                    stopped = True
                    break
                if self.mode == "online" and self._labels() >= self.options.label_budget:
                    break
                if not self.options.accelerated:
                    delay = origin + (step - first) * self.options.period_s - local_clock()
                    if delay > 0:
                        time.sleep(delay)
                more = self.step(step)
                step += 1
                self._progress(step, total)
                if not more:
                    break
            self.done = step
            if self.mode == "calibration" and self.decoder is not None:
                self.stored_recording = self.decoder.stop_recording(self._last_eeg_ts())
        finally:
            if self.decoder is not None:
                self.decoder.close()
        return self.finish(stopped)

    def _progress(self, step: int, total: int) -> None:
        now = time.monotonic()
        if now - self.last_progress < PROGRESS_EVERY_S:
            return
        self.last_progress = now
        if self.mode == "online":
            fraction = self._labels() / self.options.label_budget
        else:
            fraction = step / total
        self.context.update(steps_done=step, progress=min(fraction, 0.99))

    def end_without(self, down: ServiceDownError) -> None:
        """End the run because a service stayed down through the job's last attempt
        (:func:`~services.core.db.live.end_live_run`: its rows stay, and the run says so)."""
        with self.runtime.sessions() as db:
            end_live_run(db, self.run_id, str(down))

    def finish(self, stopped: bool) -> JobOutcome:
        if self.mode == "calibration":
            result = self.finishing.calibration(self.stored_recording)
        elif self.mode == "test":
            result = self.finishing.test(self.done)
        else:
            result = self.finishing.online(self.done, self.learner.hf_session_id)
            result["prepared_labels"] = self.learner.prepared_labels
        result["stopped_on_command"] = stopped
        status = "stopped" if stopped else "completed"
        self._set_run(status=status, result=result, finished_at=utcnow())
        with self.runtime.sessions() as db:
            lab = db.get(LabSession, self.session_id)
            assert lab is not None
            lab.status = "completed"
            db.commit()
        self.close_sim_session()
        for client in self.services.values():
            client.close()
        return JobOutcome(result=result, values={"steps_done": self.done})

    def close_sim_session(self) -> None:
        """Release the ended run's sim session (its env) now, not after the sim's idle
        timeout: a lab running more than ``max_sessions`` sessions within that hour would
        be refused (found by the soak, 409 at the ninth session). Best effort: a sim that
        is down or forgot the session has released it anyway."""
        if self.sim_session_id is None:
            return
        try:
            self.services["sim"].call_once("DELETE", f"/sessions/{self.sim_session_id}")
        except (httpx.HTTPError, ServiceCallError) as exc:
            logger.info("sim session %s not closed: %s", self.sim_session_id, exc)


def live_session(context: JobContext) -> JobOutcome:
    """Handler of ``live_session`` jobs."""
    run_id, options = _options(context)
    runner = LiveRunner(context, run_id, options)
    try:
        return runner.run()
    except JobConfigError as exc:
        runner._set_run(status="failed", error=str(exc), finished_at=utcnow())
        raise
    except ServiceDownError as exc:
        if context.attempt >= context.max_attempts:  # no attempt left to wait for it
            runner.end_without(exc)
        raise
