"""Learner service over HTTP: sessions, actions, labels, budget, idempotency, export, errors."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from services.core.platform import PlatformSettings
from services.core.settings import SettingsError, load_settings
from services.learner.feedback import FeedbackConfig
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.learner.service.settings import LearnerSettings

PAPER_FHAT = {
    "hidden_size": 16,
    "lr": 1e-3,
    "replay_updates": 16,
    "batch_size": 32,
    "newest_fraction": 0.3,
    "validation_fraction": 0.2,
    "beta": 8.0,
    "method": "paper",
    "good_accuracy": None,
    "bad_accuracy": None,
    "ensemble_size": 5,
    "thompson_period": 20,
    "revisit_window": 24,
    "kernel_bandwidth": 0.1,
    "label_channel": "hard",
    "query_certainty": 0.95,
    "query_cell_m": 0.3,
    "query_fit_period": 25,
    "query_fit_steps": 50,
    "query_final_fit_steps": 1500,
}
PLATFORM_FHAT = {**PAPER_FHAT, "method": RECOMMENDED_METHOD}
"""What a session gets by default: the paper's settings with the recommended stage-2 method."""


def observation(i: int) -> list[float]:
    """A deterministic, varied, valid 13-float observation."""
    rays = [float((i * 7 + k) % 13) for k in range(10)]
    return [*rays, 1.0 + i % 11, 0.3 * (i % 7) - 1.0, -0.2]


def create(client: TestClient, **body: object) -> dict:
    response = client.post("/hf-sessions", json=body)
    assert response.status_code == 201, response.text
    return response.json()


def label(client: TestClient, session_id: str, i: int, **extra: object):
    body = {
        "marker_id": f"m{i}",
        "observation": observation(i),
        "action": i % 3,
        "feedback": "correct" if i % 2 else "error",
        **extra,
    }
    return client.post(f"/hf-sessions/{session_id}/labels", json=body)


def test_paper_fhat_settings_are_the_learner_defaults():
    assert {k: v for k, v in FeedbackConfig().__dict__.items()} == PAPER_FHAT


def test_create_act_label_read_list(client):
    created = create(client, seed=3, label_budget=50)
    assert {k: created[k] for k in created if k not in ("id", "created_at")} == {
        "task": "sssg",
        "map": "default",
        "seed": 3,
        "method": RECOMMENDED_METHOD,
        "fhat": PLATFORM_FHAT,
        "label_budget": 50,
        "labels": 0,
        "model_version": 0,
        "metrics": {
            "training_labels": 0,
            "validation_labels": 0,
            "validation_accuracy": None,
            "validation_accuracy_true": None,
            "label_accuracy": None,
            "fhat_updates": 0,
        },
        "done": False,
    }
    sid = created["id"]
    act = client.post(f"/hf-sessions/{sid}/act", json={"observation": observation(0)})
    assert act.status_code == 200
    assert act.json()["model_version"] == 0 and act.json()["greedy"] is False
    assert act.json()["action"] in (0, 1, 2)

    for i in range(10):
        response = label(client, sid, i, oracle_correct=i % 3 != 0)
        assert response.status_code == 200, response.text
    body = response.json()
    session = client.app.state.store.get(sid)
    n_validation = len(session.learner.validation)
    assert body["labels"] == 10 and body["duplicate"] is False and body["done"] is False
    assert body["model_version"] == 10 - n_validation
    assert body["metrics"]["training_labels"] == 10 - n_validation
    assert body["metrics"]["validation_labels"] == n_validation
    # (1 + K_HF) Fhat steps per training label
    assert body["metrics"]["fhat_updates"] == 17 * (10 - n_validation)
    # labels i = 0..9: feedback "correct" iff i odd; truth iff i % 3 != 0
    agree = sum((i % 2 == 1) == (i % 3 != 0) for i in range(10))
    assert body["metrics"]["label_accuracy"] == agree / 10

    read = client.get(f"/hf-sessions/{sid}").json()
    assert read["labels"] == 10 and read["metrics"] == body["metrics"]
    assert [s["id"] for s in client.get("/hf-sessions").json()] == [sid]


def test_greedy_act_is_argmax_and_draws_nothing(client):
    sid = create(client, seed=1)["id"]
    session = client.app.state.store.get(sid)
    before = session.rng.bit_generator.state
    obs = observation(4)
    response = client.post(f"/hf-sessions/{sid}/act", json={"observation": obs, "greedy": True})
    assert response.json() == {
        "action": int(np.argmax(session.policy.scores(np.asarray(obs, np.float32)))),
        "model_version": 0,
        "greedy": True,
    }
    assert session.rng.bit_generator.state == before


@pytest.mark.parametrize("bad", ["NaN", "Infinity", "-Infinity", "1e400"])
def test_non_finite_observation_is_422_naming_the_field(client, bad):
    sid = create(client)["id"]
    raw = ", ".join(["1.0"] * 12 + [bad])
    label_fields = '"marker_id": "m", "action": 0, "feedback": "error", '
    for route, extra in (("labels", label_fields), ("act", "")):
        body = "{" + extra + f'"observation": [{raw}]' + "}"
        response = client.post(
            f"/hf-sessions/{sid}/{route}",
            content=body,
            headers={"content-type": "application/json"},
        )
        assert response.status_code == 422, response.text
        assert [e["field"] for e in response.json()["detail"]] == ["observation.12"]
    assert client.get(f"/hf-sessions/{sid}").json()["labels"] == 0


@pytest.mark.parametrize(
    ("route", "body", "field"),
    [
        ("create", {"seed": 1, "sede": 2}, "sede"),
        ("create", {"task": "xssg"}, "task"),
        ("create", {"seed": -1}, "seed"),
        ("create", {"seed": "3"}, "seed"),
        ("create", {"label_budget": 0}, "label_budget"),
        ("create", {"method": "other"}, "method"),
        ("create", {"fhat": {"lr": 0}}, "fhat.lr"),
        ("create", {"fhat": {"beta": 8, "gamma": 1}}, "fhat.gamma"),
        ("create", {"fhat": {"kernel_bandwidth": 0}}, "fhat.kernel_bandwidth"),
        ("label", {"action": 3}, "action"),
        ("label", {"action": 1.0}, "action"),
        ("label", {"feedback": "maybe"}, "feedback"),
        ("label", {"observation": [1.0] * 12}, "observation"),
        ("label", {"p_error": 1.5}, "p_error"),
        ("label", {"p_error": 0.9, "feedback": "correct"}, "p_error"),
        ("label", {"marker_id": ""}, "marker_id"),
        ("label", {"reward": 1}, "reward"),
        ("act", {"greedy": "yes"}, "greedy"),
    ],
)
def test_bad_fields_are_422_naming_the_field(client, route, body, field):
    sid = create(client)["id"]
    if route == "create":
        response = client.post("/hf-sessions", json=body)
    elif route == "label":
        base = {"marker_id": "m", "observation": observation(0), "action": 0, "feedback": "error"}
        response = client.post(f"/hf-sessions/{sid}/labels", json={**base, **body})
    else:
        body = {"observation": observation(0), **body}
        response = client.post(f"/hf-sessions/{sid}/act", json=body)
    assert response.status_code == 422, response.text
    assert [e["field"] for e in response.json()["detail"]] == [field]
    assert len(client.get("/hf-sessions").json()) == 1
    assert client.get(f"/hf-sessions/{sid}").json()["labels"] == 0


def test_service_level_refusals(make_client):
    with make_client(max_label_budget=100) as client:
        response = client.post("/hf-sessions", json={"map": "no-such-map", "label_budget": 10})
        assert response.status_code == 422 and response.json()["field"] == "map"
        response = client.post("/hf-sessions", json={"label_budget": 101})
        assert response.status_code == 422 and response.json()["field"] == "label_budget"
        response = client.get("/hf-sessions/nope")
        assert response.status_code == 404 and response.json()["field"] == "session_id"
        response = client.post("/hf-sessions/nope/act", json={"observation": observation(0)})
        assert response.status_code == 404
        assert client.get("/hf-sessions").json() == []


def test_budget_409_and_marker_ids_counted_once(client):
    sid = create(client, label_budget=3)["id"]
    assert [label(client, sid, i).json()["labels"] for i in range(3)] == [1, 2, 3]
    session = client.app.state.store.get(sid)
    weights = {k: v.clone() for k, v in session.learner.model.state_dict().items()}

    again = label(client, sid, 1)  # re-sent after a crash: counted once
    assert again.status_code == 200
    assert again.json()["duplicate"] is True and again.json()["labels"] == 3
    assert again.json()["done"] is True

    over = label(client, sid, 3)
    assert over.status_code == 409 and "budget" in over.json()["detail"]

    conflict = label(client, sid, 1, feedback="error")  # m1 was "correct"
    assert conflict.status_code == 409 and conflict.json()["field"] == "marker_id"

    assert client.get(f"/hf-sessions/{sid}").json()["labels"] == 3
    assert all(torch.equal(v, weights[k]) for k, v in session.learner.model.state_dict().items())


def test_export_is_torchscript_pt2_and_onnx_acting_like_the_greedy_policy(client, tmp_path):
    ort = pytest.importorskip("onnxruntime", reason="onnxruntime runs the ONNX file")
    sid = create(client, seed=5, fhat={"validation_fraction": 0.0})["id"]
    for i in range(12):
        assert label(client, sid, i).status_code == 200
    response = client.post(f"/hf-sessions/{sid}/export", json={})
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["model_version"] == 12 and body["metrics"]["training_labels"] == 12
    assert set(body["files"]) == {"torchscript", "pt2", "onnx"}
    paths = {}
    for fmt, stored in body["files"].items():
        paths[fmt] = PlatformSettings(data_dir=tmp_path).resolved_artifact_dir / stored["relpath"]
        data = paths[fmt].read_bytes()
        assert stored["relpath"].startswith("model/")
        assert stored["size_bytes"] == len(data)
        assert stored["sha256"] == hashlib.sha256(data).hexdigest()
    path = paths["torchscript"]

    extra = {"bgrl_meta.json": ""}
    module = torch.jit.load(str(path), _extra_files=extra)
    meta = json.loads(extra["bgrl_meta.json"])
    assert meta["model_version"] == 12 and meta["session"]["id"] == sid
    observations = [observation(i) for i in range(40)]
    greedy = [
        client.post(f"/hf-sessions/{sid}/act", json={"observation": o, "greedy": True}).json()[
            "action"
        ]
        for o in observations
    ]
    batch = module.act(torch.tensor(observations, dtype=torch.float32)).tolist()
    assert batch == greedy
    assert int(module.act(torch.tensor(observations[0]))) == greedy[0]
    assert len(set(greedy)) > 1  # the comparison covers more than one action
    session = client.app.state.store.get(sid)
    logits = session.learner.model(torch.tensor(observations)).detach()
    assert torch.equal(module(torch.tensor(observations)), logits)

    program_extra = {"bgrl_meta.json": ""}
    program = torch.export.load(str(paths["pt2"]), extra_files=program_extra).module()
    assert json.loads(program_extra["bgrl_meta.json"]) == meta
    onnx = ort.InferenceSession(str(paths["onnx"]))
    assert json.loads(onnx.get_modelmeta().custom_metadata_map["bgrl_meta.json"]) == meta
    obs = torch.tensor(observations, dtype=torch.float32)
    assert (program(obs) - logits).abs().max() < 1e-5
    (onnx_logits,) = onnx.run(["logits"], {"obs": obs.numpy()})
    assert abs(onnx_logits - logits.numpy()).max() < 1e-5
    assert torch.equal(program(obs).argmax(-1), torch.tensor(greedy))

    assert client.post(f"/hf-sessions/{sid}/export", json={"x": 1}).status_code == 422


def test_service_token_guards_every_route_but_health(make_client):
    token = "t" * 24
    with make_client(service_token=token) as client:
        assert client.get("/health").status_code == 200
        refused = client.post("/hf-sessions", json={})
        assert refused.status_code == 401 and refused.json()["field"] == "x-service-token"
        assert client.get("/hf-sessions", headers={"X-Service-Token": "w" * 24}).status_code == 401
        ok = client.post("/hf-sessions", json={}, headers={"X-Service-Token": token})
        assert ok.status_code == 201
        assert client.get("/hf-sessions", headers={"X-Service-Token": token}).status_code == 200


def test_settings_from_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("BGRL_LEARNER_PORT", "8103")
    settings = load_settings(LearnerSettings)
    assert settings.port == 8103
    assert settings.sessions_dir == Path(settings.data_dir) / "learner" / "sessions"
    monkeypatch.setenv("BGRL_LEARNER_PORT", "0")
    with pytest.raises(SettingsError, match="BGRL_LEARNER_PORT"):
        load_settings(LearnerSettings)
    monkeypatch.delenv("BGRL_LEARNER_PORT")
    assert load_settings(LearnerSettings).port == 8003


def test_kernel_bandwidth_is_a_session_setting(client):
    created = create(client, method="categorical_kernel", fhat={"kernel_bandwidth": 0.2})
    assert created["method"] == "categorical_kernel"
    assert created["fhat"]["kernel_bandwidth"] == 0.2
