"""What the learner service keeps: its HF sessions, a journal of every change and checkpoints.

Everything lives below ``<data_dir>/learner/sessions``::

    <id>/session.json   what the session was created with (task, map, seed, budget, Fhat)
    <id>/state.pt       Fhat's weights, Adam's state, the replay buffer, the validation
                        labels, both generators and every label with its marker id, as of
                        the operation count it records
    <id>/journal.jsonl  every new label and sampled action since that checkpoint

A label or sampled action is appended to the journal before it is answered (handed to the
kernel: a crash of the service cannot lose it) and synced to disk right after the answer;
``state.pt`` is rewritten (temporary name, fsync, rename) every
:attr:`~services.learner.service.settings.LearnerSettings.checkpoint_every` journal entries,
when the budget is full and after a restart, after which the journal is emptied. On start the
store reloads every session from ``state.pt`` and replays the journal entries it lacks
(:mod:`services.learner.service.journal`), so a session continues bit for bit where it
stopped.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import threading
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.core.artifacts import ArtifactStore, StoredFile
from services.core.files import write_bytes_atomic, write_json_atomic
from services.core.model_formats import SUFFIXES, ModelFormat
from services.learner.service.errors import (
    HFSessionNotFoundError,
    InvalidRequestError,
    SessionLimitError,
)
from services.learner.service.export import policy_files
from services.learner.service.journal import JOURNAL_FILE, SessionJournal, read_journal
from services.learner.service.prepared import PreparedLabel, prepare
from services.learner.service.session import HFSession, LabelOutcome, SessionSpec
from services.learner.service.settings import LearnerSettings
from services.sim.registry import resolve_map

logger = logging.getLogger(__name__)

SPEC_FILE = "session.json"
STATE_FILE = "state.pt"


class SessionStore:
    """The service's sessions in memory, mirrored on disk below ``root``."""

    def __init__(self, settings: LearnerSettings, artifacts: ArtifactStore) -> None:
        self.settings = settings
        self.root = settings.sessions_dir
        self.artifacts = artifacts
        self._sessions: dict[str, HFSession] = {}
        self._journals: dict[str, SessionJournal] = {}
        self._checkpointed_ops: dict[str, int] = {}
        """Each session's operation count in its ``state.pt``."""
        self._prepared: dict[str, PreparedLabel] = {}
        """Each session's prepared label (at most one; :mod:`.prepared`)."""
        self._lock = threading.Lock()
        self.last_checkpoint_s = 0.0
        """Seconds the last checkpoint write took (serialise + atomic write)."""

    # ------------------------------------------------------------------ start-up

    def load_all(self) -> None:
        """Reload every checkpointed session (a session that cannot be read is logged)."""
        self.root.mkdir(parents=True, exist_ok=True)
        for folder in sorted(p for p in self.root.iterdir() if p.is_dir()):
            try:
                session = self._load(folder)
            except Exception:
                logger.exception("cannot reload HF session from %s; it is skipped", folder)
                continue
            self._sessions[session.id] = session
        logger.info("%d HF session(s) reloaded from %s", len(self._sessions), self.root)

    def _load(self, folder: Path) -> HFSession:
        """The session of ``folder``: its checkpoint, then the journal entries it lacks.

        A replayed journal is folded into a new checkpoint and emptied (which also drops an
        entry cut by a crash while it was written).
        """
        spec = SessionSpec.from_json(json.loads((folder / SPEC_FILE).read_text()))
        session = HFSession(spec)
        state_path = folder / STATE_FILE
        if state_path.exists():  # absent only if the service died right after creation
            session.load_state_dict(torch.load(state_path, weights_only=True))
        self._checkpointed_ops[spec.id] = session.ops
        journal_path = folder / JOURNAL_FILE
        replayed = 0
        for entry in read_journal(journal_path):
            if entry["seq"] <= session.ops:
                continue  # in the checkpoint already (written before the journal was emptied)
            if entry["seq"] != session.ops + 1:
                raise ValueError(
                    f"journal entry {entry['seq']} does not follow operation {session.ops}"
                )
            _replay(session, entry)
            replayed += 1
        journal = SessionJournal(journal_path)
        self._journals[spec.id] = journal
        if replayed or journal_path.stat().st_size:
            self.checkpoint(session)
            journal.clear()
            logger.info("HF session %s: %d journal entries replayed", spec.id, replayed)
        return session

    # ------------------------------------------------------------------ sessions

    def create(
        self,
        *,
        task: str,
        map_spec: str | None,
        seed: int,
        label_budget: int,
        method: str,
        fhat: dict[str, Any],
    ) -> HFSession:
        """Create, checkpoint and register a new session."""
        if label_budget > self.settings.max_label_budget:
            raise InvalidRequestError(
                f"label_budget {label_budget} exceeds this service's limit of "
                f"{self.settings.max_label_budget}",
                field="label_budget",
            )
        map_name, map_path, _ = resolve_map(
            map_spec,
            tuple(self.settings.extra_map_dirs),
            self.settings.data_dir / "sim" / "oracle",
        )
        spec = SessionSpec(
            id=uuid.uuid4().hex,
            task=task,
            map=map_name,
            map_path=str(map_path),
            seed=seed,
            label_budget=label_budget,
            method=method,
            fhat=fhat,
            created_at=datetime.now(UTC).replace(microsecond=0),
        )
        try:
            session = HFSession(spec)
        except ValueError as exc:  # FeedbackConfig's own range checks
            raise InvalidRequestError(f"invalid Fhat settings: {exc}", field="fhat") from exc
        with self._lock:
            if len(self._sessions) >= self.settings.max_sessions:
                raise SessionLimitError(
                    f"this service keeps at most {self.settings.max_sessions} HF sessions"
                )
            folder = self.root / spec.id
            folder.mkdir(parents=True)
            write_json_atomic(folder / SPEC_FILE, spec.to_json())
            self.checkpoint(session)
            self._journals[spec.id] = SessionJournal(folder / JOURNAL_FILE)
            self._sessions[spec.id] = session
        logger.info("HF session %s created (%s, map %s, seed %d)", spec.id, task, map_name, seed)
        return session

    def get(self, session_id: str) -> HFSession:
        """The session with this id (404 if none)."""
        session = self._sessions.get(session_id)
        if session is None:
            raise HFSessionNotFoundError(f"no HF session {session_id!r}", field="session_id")
        return session

    def list(self) -> list[HFSession]:
        """Every session, oldest first."""
        with self._lock:
            sessions = list(self._sessions.values())
        return sorted(sessions, key=lambda s: (s.spec.created_at, s.id))

    # ------------------------------------------------------------------ labels, export

    def checkpoint(self, session: HFSession) -> None:
        """Write the session's state atomically (caller holds ``session.lock``)."""
        started = time.perf_counter()
        buffer = io.BytesIO()
        torch.save(session.state_dict(), buffer)
        write_bytes_atomic(self.root / session.id / STATE_FILE, buffer.getvalue())
        self._checkpointed_ops[session.id] = session.ops
        self.last_checkpoint_s = time.perf_counter() - started

    def add_label(
        self,
        session: HFSession,
        next_observation: list[float] | None = None,
        *,
        marker_id: str,
        observation: list[float],
        action: int,
        correct: bool,
        p_error: float | None = None,
        oracle_correct: bool | None = None,
        log_likelihood_ratio: float | None = None,
    ) -> tuple[LabelOutcome, int | None]:
        """Add a label and journal it; with ``next_observation`` also sample pi_HF's next
        action from the updated Fhat (unless the budget is full).

        Returns the outcome and the action. A label prepared with :meth:`prepare_label` has
        its update swapped in, not run (``outcome.prepared``). Nothing is synced
        here: call :meth:`persist` after answering. If the journal cannot be written, the
        session is reloaded from its files (the label is undone) and the error raised.
        """
        _check_observations(session, observation, next_observation)
        with session.lock:
            prepared = self._prepared.pop(session.id, None)
            obs = np.asarray(observation, dtype=np.float32)
            outcome = session.check_label(
                marker_id, obs, action, correct, p_error, oracle_correct, log_likelihood_ratio
            )
            if outcome is not None:  # a duplicate
                return outcome, self._next_action(session, next_observation)
            used = prepared is not None and prepared.matches(
                marker_id, observation, action, oracle_correct, next_observation, session.ops
            )
            next_action = None
            if used:
                ready = prepared.outcomes[correct]
                sampled = ready.next_action is not None
                outcome = session.add_forked_label(
                    marker_id,
                    ready.learner,
                    ready.rng,
                    ready.fed,
                    p_error,
                    sampled,
                    log_likelihood_ratio,
                )
                next_action = ready.next_action
            else:
                outcome = session.add_label(
                    marker_id,
                    observation,
                    action,
                    correct,
                    p_error,
                    oracle_correct,
                    log_likelihood_ratio,
                )
            record = outcome.record
            entry = {
                "op": "label",
                "marker_id": record.marker_id,
                "observation": observation,
                "action": record.action,
                "correct": record.correct,
                "p_error": record.p_error,
                "oracle_correct": record.oracle_correct,
                "log_likelihood_ratio": record.log_likelihood_ratio,
            }
            if used and next_action is not None:  # journal both operations, as below
                self._journal(session, entry, seq=session.ops - 1)
                self._journal(session, {"op": "act", "observation": next_observation})
                return outcome, next_action
            self._journal(session, entry)
            if not used:
                next_action = self._next_action(session, next_observation)
            return outcome, next_action

    def prepare_label(
        self,
        session: HFSession,
        *,
        marker_id: str,
        observation: list[float],
        action: int,
        oracle_correct: bool | None = None,
        next_observation: list[float] | None = None,
    ) -> bool:
        """Compute the session after this label for both feedback values (and pi_HF's next
        action in ``next_observation``), so that the label itself only swaps one in.

        The updates run on copies, outside the session's lock; the result replaces the
        session's prepared label if the session did not change meanwhile. Returns whether a
        label was prepared: not for a marker labelled before or once the budget is full
        (the label then takes the ordinary path and answers as it does).
        """
        _check_observations(session, observation, next_observation)
        with session.lock:
            # a soft label's update needs its ratio, which is not known in advance
            if session.labels.get(marker_id) is not None or session.done or session.learner.soft:
                return False
            ops = session.ops
            sample_next = len(session.labels) + 1 < session.spec.label_budget
            forks = {True: session.fork(), False: session.fork()}
        prepared = prepare(
            forks,
            marker_id=marker_id,
            observation=observation,
            action=action,
            oracle_correct=oracle_correct,
            next_observation=next_observation,
            sample_next=sample_next,
            ops=ops,
        )
        with session.lock:
            if session.ops != ops:
                return False
            self._prepared[session.id] = prepared
        return True

    def act(self, session: HFSession, observation: list[float], greedy: bool) -> tuple[int, int]:
        """pi_HF's action and the model version it came from.

        A sampled action advances the sampling generator and is journaled (a greedy one
        changes nothing).
        """
        session.check_observation(observation)
        with session.lock:
            if greedy:
                return session.act(observation, greedy=True), session.model_version
            self._prepared.pop(session.id, None)
            return self._sample(session, observation), session.model_version

    def persist(self, session: HFSession) -> None:
        """Make the session's journal durable, and checkpoint it once ``checkpoint_every``
        entries have been journaled and when its budget is full (then the journal is
        emptied).

        Run after the answer: the journal entries are already safe from a crash of the
        service, this protects them from a crash of the machine and bounds the replay. A
        failed checkpoint is logged and tried again at the next call (the journal keeps
        everything meanwhile).
        """
        with session.lock:
            journal = self._journals.get(session.id)
            if journal is None:  # the store was closed (shutdown)
                return
            journal.sync()
            due = session.ops - self._checkpointed_ops[session.id]
            if due == 0 or (due < self.settings.checkpoint_every and not session.done):
                return
            try:
                self.checkpoint(session)
            except Exception:
                logger.exception("checkpoint of HF session %s failed", session.id)
                return
            journal.clear()

    def close(self) -> None:
        """Sync and close every journal (at shutdown)."""
        with self._lock:
            for journal in self._journals.values():
                journal.close()
            self._journals.clear()

    def _next_action(self, session: HFSession, next_observation: list[float] | None) -> int | None:
        """pi_HF's sampled action in ``next_observation`` unless none was asked for or the
        budget is full."""
        if next_observation is None or session.done:
            return None
        return self._sample(session, next_observation)

    def _sample(self, session: HFSession, observation: list[float]) -> int:
        action = session.act(observation, greedy=False)
        self._journal(session, {"op": "act", "observation": observation})
        return action

    def _journal(self, session: HFSession, entry: dict[str, Any], seq: int | None = None) -> None:
        """Append ``entry`` as operation ``seq`` (default ``session.ops``); on failure,
        reload and raise."""
        try:
            self._journals[session.id].append({"seq": session.ops if seq is None else seq, **entry})
        except BaseException:
            logger.exception("journal of HF session %s cannot be written", session.id)
            with contextlib.suppress(OSError):  # what was written is read back below
                self._journals.pop(session.id).close()
            restored = self._load(self.root / session.id)
            session.load_state_dict(restored.state_dict())
            raise

    def export(
        self, session: HFSession
    ) -> tuple[dict[ModelFormat, StoredFile], int, dict[str, Any]]:
        """Store the greedy pi_HF in the artifact store (kind ``model``) in every format
        (TorchScript, ``.pt2``, ONNX)."""
        with session.lock:
            version = session.model_version
            metrics = session.model_metrics()
            meta = {
                "kind": "hf_policy",
                "session": session.spec.to_json(),
                "labels": len(session.labels),
                "model_version": version,
                "metrics": metrics,
            }
            files = policy_files(session.learner.model, meta)
        stored = {
            fmt: self.artifacts.put_bytes(
                data, kind="model", name=f"hf_policy_{session.id}_v{version}{SUFFIXES[fmt]}"
            )
            for fmt, data in files.items()
        }
        logger.info("HF session %s exported as %s", session.id, stored["torchscript"].relpath)
        return stored, version, metrics


def _check_observations(
    session: HFSession, observation: list[float], next_observation: list[float] | None
) -> None:
    """Refuse a request whose observations are not the env's (nothing changes)."""
    session.check_observation(observation)
    if next_observation is not None:
        session.check_observation(next_observation, "next_observation")


def _replay(session: HFSession, entry: dict[str, Any]) -> None:
    """Apply one journal entry to ``session`` again."""
    if entry["op"] == "label":
        session.add_label(
            marker_id=entry["marker_id"],
            observation=entry["observation"],
            action=entry["action"],
            correct=entry["correct"],
            p_error=entry["p_error"],
            oracle_correct=entry["oracle_correct"],
            log_likelihood_ratio=entry.get("log_likelihood_ratio"),  # absent in older journals
        )
    elif entry["op"] == "act":
        session.act(entry["observation"], greedy=False)
    else:
        raise ValueError(f"unknown journal operation {entry['op']!r}")
