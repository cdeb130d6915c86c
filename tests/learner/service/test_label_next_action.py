"""A label carrying ``next_observation`` answers pi_HF's next action: the same action, the
same Fhat and the same sampling stream as a label followed by ``POST /act``."""

from __future__ import annotations

import torch

from tests.learner.service.test_app import create, label, observation

N_LABELS = 12


def _state(client, session_id: str) -> dict:
    return client.app.state.store.get(session_id).state_dict()


def test_next_action_in_the_label_answer_equals_a_separate_act(make_client, tmp_path):
    with (
        make_client(data_dir=tmp_path / "a") as two_calls,
        make_client(data_dir=tmp_path / "b") as one_call,
    ):
        a = create(two_calls, seed=3, label_budget=N_LABELS)["id"]
        b = create(one_call, seed=3, label_budget=N_LABELS)["id"]
        for i in range(N_LABELS):
            first = label(two_calls, a, i)
            assert first.status_code == 200, first.text
            assert first.json()["next_action"] is None
            merged = label(one_call, b, i, next_observation=observation(i + 1))
            assert merged.status_code == 200, merged.text
            if i + 1 < N_LABELS:
                act = two_calls.post(
                    f"/hf-sessions/{a}/act", json={"observation": observation(i + 1)}
                )
                assert merged.json()["next_action"] == act.json()["action"]
            else:  # the budget is full: no action is drawn
                assert merged.json()["done"] and merged.json()["next_action"] is None
        state_a = _state(two_calls, a)
        state_b = _state(one_call, b)
    assert state_a["sampling_rng"] == state_b["sampling_rng"]
    for name, tensor in state_a["learner"]["model"].items():
        assert torch.equal(tensor, state_b["learner"]["model"][name]), name


def test_bad_next_observation_is_422_naming_the_field(client):
    session_id = create(client, seed=0, label_budget=4)["id"]
    response = label(client, session_id, 0, next_observation=[0.0, 1.0])
    assert response.status_code == 422
    assert "next_observation" in response.text
    assert client.get(f"/hf-sessions/{session_id}").json()["labels"] == 0
