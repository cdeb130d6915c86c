"""HFSession and the store below HTTP: state round trips and a failed journal write."""

from __future__ import annotations

from dataclasses import asdict
from datetime import UTC, datetime

import gymnasium as gym
import numpy as np
import pytest
import torch

import services.sim  # noqa: F401  (registers the env ids)
from services.core.artifacts import ArtifactStore
from services.learner.feedback import FeedbackConfig
from services.learner.networks import ObsNormalizer
from services.learner.service.journal import SessionJournal
from services.learner.service.session import HFSession, SessionSpec, observation_space
from services.learner.service.settings import LearnerSettings
from services.learner.service.store import SessionStore
from services.sim.maps import DEFAULT_MAP_PATH, load_map


def _spec(session_id: str = "s1", seed: int = 2) -> SessionSpec:
    return SessionSpec(
        id=session_id,
        task="sssg",
        map="default",
        map_path=str(DEFAULT_MAP_PATH),
        seed=seed,
        label_budget=100,
        method="paper",
        fhat=asdict(FeedbackConfig()),
        created_at=datetime(2026, 1, 1, tzinfo=UTC),
    )


def _label(session: HFSession, i: int) -> None:
    obs = [float((3 * i + k) % 13) for k in range(10)] + [4.0, 0.2 * (i % 9) - 0.8, 0.3]
    action = session.act(obs, greedy=False)
    session.add_label(f"m{i}", obs, action, bool(i % 3), p_error=None, oracle_correct=bool(i % 2))


def _weights(session: HFSession) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in session.learner.model.state_dict().items()}


def test_observation_space_is_the_envs():
    env = gym.make("services.sim:BrainNav-SSSG-v0")
    try:
        ours = observation_space(load_map(DEFAULT_MAP_PATH))
        assert np.array_equal(ours.low, env.observation_space.low)
        assert np.array_equal(ours.high, env.observation_space.high)
        a = ObsNormalizer.from_space(ours)
        b = ObsNormalizer.from_space(env.observation_space)
        assert torch.equal(a.offset, b.offset) and torch.equal(a.scale, b.scale)
    finally:
        env.close()


def test_state_dict_round_trip_continues_identically():
    reference, resumed = HFSession(_spec()), HFSession(_spec())
    for i in range(12):
        _label(reference, i)
        _label(resumed, i)
    state = resumed.state_dict()
    restored = HFSession(_spec())
    restored.load_state_dict(state)
    for i in range(12, 20):
        _label(reference, i)
        _label(restored, i)
    assert restored.labels.records == reference.labels.records
    ref, got = _weights(reference), _weights(restored)
    assert all(torch.equal(ref[k], got[k]) for k in ref)
    assert restored.metrics() == reference.metrics()


def test_failed_journal_write_undoes_the_label(tmp_path, monkeypatch):
    settings = LearnerSettings(data_dir=tmp_path)
    store = SessionStore(settings, ArtifactStore(tmp_path / "artifacts"))
    store.load_all()
    session = store.create(
        task="sssg",
        map_spec=None,
        seed=2,
        label_budget=100,
        method="paper",
        fhat=asdict(FeedbackConfig()),
    )
    reference = HFSession(session.spec)
    obs = [5.0] * 10 + [3.0, 0.1, 0.2]
    for i in range(5):
        store.add_label(session, marker_id=f"m{i}", observation=obs, action=i % 3, correct=True)
        reference.add_label(f"m{i}", obs, i % 3, True)
    before = _weights(session)

    def disk_full(journal, entry):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(SessionJournal, "append", disk_full)
    with pytest.raises(OSError):
        store.add_label(session, marker_id="m5", observation=obs, action=1, correct=False)
    assert len(session.labels) == 5 and session.labels.get("m5") is None
    assert all(torch.equal(v, before[k]) for k, v in _weights(session).items())
    monkeypatch.undo()

    store.add_label(session, marker_id="m5", observation=obs, action=1, correct=False)
    reference.add_label("m5", obs, 1, False)
    ref = _weights(reference)
    assert all(torch.equal(v, ref[k]) for k, v in _weights(session).items())
