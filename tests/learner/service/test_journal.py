"""The journal: a learner killed right after answering loses nothing, and the session it
restores continues bit for bit; a cut last entry is dropped; checkpoints bound the journal."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from services.core.artifacts import ArtifactStore
from services.learner.service.journal import JOURNAL_FILE, read_journal
from services.learner.service.session import HFSession
from services.learner.service.settings import LearnerSettings
from services.learner.service.store import STATE_FILE, SessionStore
from tests.learner.service.test_app import create, label, observation


def _restarted(data_dir: Path, **settings: Any) -> SessionStore:
    """A second store on the same files, as a service started after a crash loads them."""
    store = SessionStore(
        LearnerSettings(data_dir=data_dir, **settings), ArtifactStore(data_dir / "artifacts")
    )
    store.load_all()
    return store


def _assert_same_state(a: HFSession, b: HFSession) -> None:
    state_a, state_b = a.state_dict(), b.state_dict()
    assert state_a["ops"] == state_b["ops"]
    assert state_a["sampling_rng"] == state_b["sampling_rng"]
    learner_a, learner_b = state_a["learner"], state_b["learner"]
    assert learner_a["rng"] == learner_b["rng"]
    assert learner_a["n_updates"] == learner_b["n_updates"]
    for key in ("model", "buffer", "validation"):
        for name, tensor in learner_a[key].items():
            assert torch.equal(learner_b[key][name], tensor), (key, name)
    for index, slot in learner_a["optimizer"]["state"].items():
        for name, tensor in slot.items():
            assert torch.equal(learner_b["optimizer"]["state"][index][name], tensor)
    assert a.labels.records == b.labels.records


def test_a_learner_killed_right_after_answering_loses_nothing(make_client, tmp_path, monkeypatch):
    with make_client(data_dir=tmp_path) as client:
        store: SessionStore = client.app.state.store
        # killed after each answer, before its sync and checkpoint: persist never runs
        monkeypatch.setattr(store, "persist", lambda session: None)
        sid = create(client, seed=5, label_budget=40)["id"]
        client.post(f"/hf-sessions/{sid}/act", json={"observation": observation(0)})
        for i in range(20):
            answer = label(client, sid, i, next_observation=observation(i + 1))
            assert answer.status_code == 200, answer.text
        live = store.get(sid)
        assert torch.load(tmp_path / "learner" / "sessions" / sid / STATE_FILE)["ops"] == 0

        restarted = _restarted(tmp_path)
        restored = restarted.get(sid)
        _assert_same_state(live, restored)  # every answered label and action is back
        # replayed into a new checkpoint, the journal emptied
        assert read_journal(tmp_path / "learner" / "sessions" / sid / JOURNAL_FILE) == []

        # the worker re-sends the last answered label: counted once, nothing changes
        again, _ = restarted.add_label(
            restored,
            marker_id="m19",
            observation=observation(19),
            action=19 % 3,
            correct=True,
            p_error=None,
            oracle_correct=None,
        )
        assert again.duplicate
        # both continue identically: the same next actions and the same Fhat
        for i in range(20, 30):
            answer = label(client, sid, i, next_observation=observation(i + 1)).json()
            outcome, action = restarted.add_label(
                restored,
                next_observation=observation(i + 1),
                marker_id=f"m{i}",
                observation=observation(i),
                action=i % 3,
                correct=bool(i % 2),
                p_error=None,
                oracle_correct=None,
            )
            assert (action, outcome.record.validation) == (
                answer["next_action"],
                answer["validation"],
            )
        _assert_same_state(live, restored)
        restarted.close()


def test_an_entry_cut_by_a_crash_is_dropped(make_client, tmp_path):
    with make_client(data_dir=tmp_path) as client:
        sid = create(client, seed=1, label_budget=10)["id"]
        for i in range(3):
            assert label(client, sid, i).status_code == 200
        before = client.app.state.store.get(sid).state_dict()
    journal = tmp_path / "learner" / "sessions" / sid / JOURNAL_FILE
    entries = read_journal(journal)
    assert [e["op"] for e in entries] == ["label"] * 3
    with journal.open("ab") as fh:  # the crash cut the fourth label's line
        fh.write(b'{"seq":4,"op":"label","marker_id":"m3","obs')
    with make_client(data_dir=tmp_path) as client:
        restored = client.app.state.store.get(sid)
        assert restored.ops == before["ops"] == 3 and len(restored.labels) == 3
        assert journal.stat().st_size == 0
        assert label(client, sid, 3).status_code == 200  # the worker re-sends it


def test_checkpoints_bound_the_journal(make_client, tmp_path):
    with make_client(data_dir=tmp_path, checkpoint_every=4) as client:
        sid = create(client, seed=3, label_budget=9)["id"]
        folder = tmp_path / "learner" / "sessions" / sid
        for i in range(9):
            assert label(client, sid, i, next_observation=observation(i + 1)).status_code == 200
            ops = client.app.state.store.get(sid).ops
            in_checkpoint = torch.load(folder / STATE_FILE)["ops"]
            assert ops - in_checkpoint == len(read_journal(folder / JOURNAL_FILE)) < 4
        # the budget is full: the final state is in the checkpoint, the journal empty
        assert torch.load(folder / STATE_FILE)["ops"] == ops
        assert read_journal(folder / JOURNAL_FILE) == []


def test_a_checkpoint_from_before_the_journal_loads_counting_no_operations(make_client):
    with make_client() as client:
        sid = create(client, seed=2, label_budget=10)["id"]
        for i in range(4):
            assert label(client, sid, i).status_code == 200
        session = client.app.state.store.get(sid)
        state = session.state_dict()
    old = {**{k: v for k, v in state.items() if k != "ops"}, "format": 1}
    restored = HFSession(session.spec)
    restored.load_state_dict(old)
    assert restored.ops == 0 and restored.labels.records == session.labels.records
    assert torch.equal(restored.learner.model.hidden.weight, session.learner.model.hidden.weight)
