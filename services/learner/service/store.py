"""What the learner service keeps: its HF sessions, checkpointed after every label.

Everything lives below ``<data_dir>/learner/sessions``::

    <id>/session.json   what the session was created with (task, map, seed, budget, Fhat)
    <id>/state.pt       Fhat's weights, Adam's state, the replay buffer, the validation
                        labels, both generators and every label with its marker id

Both files are written under a temporary name and renamed (``state.pt`` after every label),
so a crash leaves the state after the last answered label, never half a file. On start the
store reloads every session from these files.
"""

from __future__ import annotations

import io
import json
import logging
import threading
import time
import uuid
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import torch

from services.core.artifacts import ArtifactStore, StoredFile
from services.core.files import write_bytes_atomic, write_json_atomic
from services.learner.service.errors import (
    HFSessionNotFoundError,
    InvalidRequestError,
    SessionLimitError,
)
from services.learner.service.export import torchscript_bytes
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
        spec = SessionSpec.from_json(json.loads((folder / SPEC_FILE).read_text()))
        session = HFSession(spec)
        state_path = folder / STATE_FILE
        if state_path.exists():  # absent only if the service died right after creation
            session.load_state_dict(torch.load(state_path, weights_only=True))
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
        self.last_checkpoint_s = time.perf_counter() - started

    def add_label(self, session: HFSession, **label: Any) -> LabelOutcome:
        """Add a label and checkpoint; if the checkpoint fails, the label is undone."""
        with session.lock:
            outcome = session.add_label(**label)
            if outcome.duplicate:
                return outcome
            try:
                self.checkpoint(session)
            except BaseException:
                logger.exception("checkpoint of HF session %s failed", session.id)
                session.load_state_dict(
                    torch.load(self.root / session.id / STATE_FILE, weights_only=True)
                )
                raise
            return outcome

    def act(self, session: HFSession, observation: list[float], greedy: bool) -> tuple[int, int]:
        """pi_HF's action and the model version it came from.

        A sampled action advances the sampling generator, which is checkpointed with the next
        label (an action whose label never arrives leaves no trace once the service restarts,
        as an action that was never asked for).
        """
        with session.lock:
            return session.act(observation, greedy), session.model_version

    def export(self, session: HFSession) -> tuple[StoredFile, int, dict[str, Any]]:
        """Store the TorchScript greedy pi_HF in the artifact store (kind ``model``)."""
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
            data = torchscript_bytes(session.learner.model, meta)
        stored = self.artifacts.put_bytes(
            data, kind="model", name=f"hf_policy_{session.id}_v{version}.pt"
        )
        logger.info("HF session %s exported as %s", session.id, stored.relpath)
        return stored, version, metrics
