"""Prepared labels (``POST /labels/prepare``): the session after a prepared label is bit for
bit the session after the same label unprepared, for both feedback values, held-out labels,
the recommended method and the paper's; its journal and checkpoint are the same files."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from services.learner.hf_methods import RECOMMENDED_METHOD
from services.learner.service.journal import JOURNAL_FILE
from services.learner.service.store import STATE_FILE
from tests.learner.service.test_app import create, label, observation
from tests.learner.service.test_journal import _restarted

N_LABELS = 14


def assert_identical(a: Any, b: Any, where: str = "state") -> None:
    """Every tensor and array bit for bit (``torch.equal`` on their bytes: NaN included),
    everything else ``==``."""
    assert type(a) is type(b), where
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_identical(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for index, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_identical(x, y, f"{where}[{index}]")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape, where
        assert torch.equal(_bytes(a), _bytes(b)), where
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
    else:
        assert a == b, where


def _bytes(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.reshape(-1).contiguous().view(torch.uint8)


def _prepare(client, sid: str, i: int, **extra: Any):
    body = {"marker_id": f"m{i}", "observation": observation(i), "action": i % 3, **extra}
    return client.post(f"/hf-sessions/{sid}/labels/prepare", json=body)


def _feedback(i: int) -> str:
    return "error" if i % 3 == 1 else "correct"


def _session_dir(data_dir: Path, sid: str) -> Path:
    return data_dir / "learner" / "sessions" / sid


@pytest.mark.parametrize("method", [RECOMMENDED_METHOD, "paper"])
def test_a_prepared_label_leaves_the_session_the_unprepared_one_does(make_client, tmp_path, method):
    plain_dir, prepared_dir = tmp_path / "plain", tmp_path / "prepared"
    with (
        make_client(data_dir=plain_dir, checkpoint_every=5) as plain,
        make_client(data_dir=prepared_dir, checkpoint_every=5) as ready,
    ):
        a = create(plain, seed=4, label_budget=N_LABELS, method=method)["id"]
        b = create(ready, seed=4, label_budget=N_LABELS, method=method)["id"]
        held_out = set()
        for i in range(N_LABELS):
            extra = {"oracle_correct": i % 2 == 0, "next_observation": observation(i + 1)}
            prepared = _prepare(ready, b, i, **extra)
            assert prepared.status_code == 200 and prepared.json() == {"prepared": True}
            kw = {"feedback": _feedback(i), **extra}
            expected = label(plain, a, i, **kw).json()
            answer = label(ready, b, i, **kw).json()
            assert answer.pop("prepared") is True and expected.pop("prepared") is False
            assert answer == expected
            if answer["validation"]:
                held_out.add(i)
            assert_identical(
                plain.app.state.store.get(a).state_dict(),
                ready.app.state.store.get(b).state_dict(),
                f"after label {i}",
            )
        assert held_out and len(held_out) < N_LABELS  # both kinds were prepared
        assert {_feedback(i) for i in range(N_LABELS)} == {"correct", "error"}
    for name in (JOURNAL_FILE, STATE_FILE):
        plain_bytes = (_session_dir(plain_dir, a) / name).read_bytes()
        assert plain_bytes == (_session_dir(prepared_dir, b) / name).read_bytes(), name


def test_a_restart_replays_a_journal_of_prepared_labels(make_client, tmp_path, monkeypatch):
    with make_client(data_dir=tmp_path) as client:
        store = client.app.state.store
        monkeypatch.setattr(store, "persist", lambda session: None)  # killed after answers
        sid = create(client, seed=2, label_budget=20)["id"]
        for i in range(6):
            extra = {"next_observation": observation(i + 1)}
            assert _prepare(client, sid, i, **extra).json()["prepared"]
            assert label(client, sid, i, feedback=_feedback(i), **extra).json()["prepared"]
        live = store.get(sid).state_dict()
    assert_identical(live, _restarted(tmp_path).get(sid).state_dict())


def test_the_fork_shares_no_tensor_or_generator_with_the_session(client):
    sid = create(client, seed=1, label_budget=10)["id"]
    for i in range(3):
        label(client, sid, i)
    session = client.app.state.store.get(sid)
    learner, rng = session.fork()
    assert rng is not session.rng and learner.rng is not session.learner.rng
    assert rng.bit_generator.state == session.rng.bit_generator.state
    for x, y in zip(session.learner.model.parameters(), learner.model.parameters(), strict=True):
        assert torch.equal(x, y) and x.data_ptr() != y.data_ptr()
    for name in ("obs", "actions", "labels"):
        x, y = getattr(session.learner.buffer, name), getattr(learner.buffer, name)
        assert np.array_equal(x, y) and not np.shares_memory(x, y), name
    for slot in learner.optimizer.state.values():
        for tensor in slot.values():
            assert all(tensor.data_ptr() != t.data_ptr() for t in _optimizer_tensors(session))
    optimizer_params = [p for group in learner.optimizer.param_groups for p in group["params"]]
    assert all(any(p is q for q in learner.model.parameters()) for p in optimizer_params)
    assert learner.policy.model is learner.model
    before = session.state_dict()
    learner.add(np.asarray(observation(9), np.float32), 0, False)
    learner.collection_action(np.asarray(observation(9), np.float32), rng)
    assert_identical(before, session.state_dict())  # learning on the fork left it unchanged


def _optimizer_tensors(session) -> list[torch.Tensor]:
    return [t for slot in session.learner.optimizer.state.values() for t in slot.values()]


def test_a_label_that_differs_or_a_changed_session_takes_the_ordinary_path(client):
    sid = create(client, seed=0, label_budget=4)["id"]
    session = client.app.state.store.get(sid)
    assert _prepare(client, sid, 0).json()["prepared"]
    # another action first: the session changed, the prepared label is dropped
    client.post(f"/hf-sessions/{sid}/act", json={"observation": observation(5)})
    assert client.app.state.store._prepared == {}
    assert label(client, sid, 0).json()["prepared"] is False
    # different fields (here the next observation) than prepared
    assert _prepare(client, sid, 1, next_observation=observation(2)).json()["prepared"]
    assert label(client, sid, 1, next_observation=observation(3)).json()["prepared"] is False
    # a marker labelled before is not prepared; the label answers as a duplicate
    assert _prepare(client, sid, 1).json() == {"prepared": False}
    assert label(client, sid, 1).json()["duplicate"] is True
    # one prepared label per session: the newest replaces the older
    assert _prepare(client, sid, 2).json()["prepared"]
    assert _prepare(client, sid, 3).json()["prepared"]
    assert label(client, sid, 2).json()["prepared"] is False
    assert label(client, sid, 3).json()["prepared"] is False  # dropped by label 2
    assert session.done and _prepare(client, sid, 4).json() == {"prepared": False}
    assert (
        client.post(f"/hf-sessions/{sid}/labels/prepare", json={"marker_id": "x"}).status_code
        == 422
    )
