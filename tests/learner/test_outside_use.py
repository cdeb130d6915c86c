"""The learner as outside code uses it: the HF service fed observations that are not the
env's, exported policies run on numpy float64 and batches, checkpoints that are truncated
or carry code, and the in-process policies given a batch."""

from __future__ import annotations

import io
import json
import os
import pickle
from collections.abc import Iterator
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient

from services.core.platform import PlatformSettings
from services.learner.checkpoint import load_checkpoint
from services.learner.feedback import FeedbackConfig, FeedbackLearner, HFPolicy
from services.learner.networks import ObsNormalizer
from services.learner.ppo import PPOConfig, train
from services.learner.service.app import create_app
from services.learner.service.settings import LearnerSettings
from tests.learner.conftest import ToyGridEnv
from tests.learner.service.test_app import create, label, observation

# --------------------------------------------------------------------------- the service


@pytest.fixture
def client(tmp_path: Path) -> Iterator[TestClient]:
    settings = LearnerSettings(data_dir=tmp_path, log_level="WARNING")
    app = create_app(settings, PlatformSettings(data_dir=tmp_path))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


def _state(client: TestClient, sid: str) -> dict[str, Any]:
    """What a request that is refused must leave as it was."""
    session = client.app.state.store.get(sid)
    return {
        "ops": session.ops,
        "labels": len(session.labels),
        "weights": {k: v.clone() for k, v in session.learner.model.state_dict().items()},
        "sampling": json.dumps(session.rng.bit_generator.state),
        "split": json.dumps(session.learner.rng.bit_generator.state),
    }


def _assert_same(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert {k: a[k] for k in a if k != "weights"} == {k: b[k] for k in b if k != "weights"}
    assert all(torch.equal(a["weights"][k], b["weights"][k]) for k in a["weights"])


def test_a_label_whose_observation_overflows_float32_is_refused_and_changes_nothing(client):
    """1e39 is a finite JSON number but infinite in float32: the update made every weight of
    Fhat NaN for good (and pi_HF then always answered action 0)."""
    sid = create(client, seed=1, fhat={"validation_fraction": 0.0})["id"]
    for i in range(3):
        assert label(client, sid, i).status_code == 200
    prepared = {"marker_id": "m3", "observation": observation(3), "action": 0}
    assert client.post(f"/hf-sessions/{sid}/labels/prepare", json=prepared).json()["prepared"]
    before = _state(client, sid)

    bad = {"marker_id": "big", "observation": [1e39] * 13, "action": 0, "feedback": "error"}
    response = client.post(f"/hf-sessions/{sid}/labels", json=bad)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "observation.0"
    assert "outside the env's range [0, 13]" in response.json()["detail"]
    _assert_same(before, _state(client, sid))

    # the prepared label survived the refused one, and Fhat still learns finite weights
    answer = label(client, sid, 3, action=0, feedback="error")
    assert answer.status_code == 200 and answer.json()["prepared"] is True
    weights = client.app.state.store.get(sid).learner.model.state_dict().values()
    assert all(torch.isfinite(w).all() for w in weights)


@pytest.mark.parametrize(
    ("route", "body", "field"),
    [
        ("act", {"observation": [*observation(0)[:12], 7.0]}, "observation.12"),  # yaw > pi
        ("act", {"observation": [1e300] * 13, "greedy": True}, "observation.0"),
        (
            "labels",
            {
                "marker_id": "n",
                "observation": observation(0),
                "action": 1,
                "feedback": "correct",
                "next_observation": [*observation(1)[:10], -1.0, 0.0, 0.0],  # distance < 0
            },
            "next_observation.10",
        ),
        (
            "labels/prepare",
            {"marker_id": "p", "observation": [*observation(2)[:11], -4.0, 0.0], "action": 2},
            "observation.11",
        ),
    ],
)
def test_observations_outside_the_envs_space_are_422_naming_the_element(
    client, route: str, body: dict, field: str
):
    sid = create(client, seed=2)["id"]
    assert label(client, sid, 0).status_code == 200
    before = _state(client, sid)
    response = client.post(f"/hf-sessions/{sid}/{route}", json=body)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    _assert_same(before, _state(client, sid))


def test_observation_values_must_be_json_numbers(client):
    sid = create(client)["id"]
    for value in ("1", True):
        body = {"observation": [*observation(0)[:12], value]}
        response = client.post(f"/hf-sessions/{sid}/act", json=body)
        assert response.status_code == 422, response.text
        assert [e["field"] for e in response.json()["detail"]] == ["observation.12"]
    assert client.app.state.store.get(sid).ops == 0


def test_observations_on_the_boundary_of_the_space_are_accepted(client):
    sid = create(client)["id"]
    edge = [13.0] * 10 + [0.0, -np.pi, np.pi]  # the env's bounds, given as float64
    response = client.post(f"/hf-sessions/{sid}/act", json={"observation": edge, "greedy": True})
    assert response.status_code == 200, response.text


def test_a_map_name_with_a_nul_byte_is_a_422_naming_map(client):
    response = client.post("/hf-sessions", json={"map": "default\u0000"})
    assert response.status_code == 422, response.text
    assert response.json()["field"] == "map"
    assert client.get("/hf-sessions").json() == []


def test_exported_pi_hf_takes_float64_single_and_batched_observations(client, tmp_path):
    sid = create(client, seed=5, fhat={"validation_fraction": 0.0})["id"]
    for i in range(8):
        assert label(client, sid, i).status_code == 200
    exported = client.post(f"/hf-sessions/{sid}/export", json={}).json()
    relpath = exported["files"]["torchscript"]["relpath"]
    module = torch.jit.load(
        str(PlatformSettings(data_dir=tmp_path).resolved_artifact_dir / relpath)
    )
    batch = np.array([observation(i) for i in range(6)], dtype=np.float64)
    expected = module.act(torch.from_numpy(batch.astype(np.float32)))
    assert torch.equal(module.act(torch.from_numpy(batch)), expected)  # float64 batch
    assert int(module.act(torch.from_numpy(batch[0]))) == int(expected[0])  # float64 single
    nested = module.act(torch.from_numpy(batch.reshape(2, 3, 13)))
    assert torch.equal(nested.reshape(-1), expected)
    with pytest.raises(torch.jit.Error, match=r"expected raw observations of shape \(13,\)"):
        module.act(torch.zeros(12))


# --------------------------------------------------------------------------- PPO and pi_HF


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[PPOConfig, Any, Path]:
    """A tiny PPO run on the toy grid with a checkpoint after every update."""
    from tests.learner.conftest import toy_config

    config = toy_config(total_steps=256, n_epochs=1)
    checkpoint = tmp_path_factory.mktemp("run") / "checkpoint.pt"
    return config, train(config, checkpoint_path=checkpoint, checkpoint_every=1), checkpoint


def test_exported_ppo_policy_takes_float64_single_and_batched_observations(trained, tmp_path):
    _, result, _ = trained
    module = torch.jit.load(str(result.export_torchscript(tmp_path / "policy.pt")))
    obs = np.array([[0, 0, 0, 1, 0], [1, 2, 1, 0, 1], [3, 3, 2, -1, 0]], dtype=np.float64)
    expected = module(torch.from_numpy(obs.astype(np.float32)))
    assert torch.equal(module(torch.from_numpy(obs)), expected)
    assert torch.allclose(module(torch.from_numpy(obs[1])), expected[1], atol=1e-6)
    assert torch.equal(module.act(torch.from_numpy(obs)), expected.argmax(-1))
    assert module.act(torch.from_numpy(np.stack([obs, obs]))).shape == (2, 3)
    assert int(module.act(torch.from_numpy(obs[2]))) == result.act(obs[2])
    with pytest.raises(torch.jit.Error, match=r"expected raw observations of shape \(5,\)"):
        module(torch.zeros(13))


def test_in_process_policies_refuse_a_batch_instead_of_a_wrong_action(trained):
    """``int(argmax)`` over a batch's logits was an index into the flattened batch."""
    _, result, _ = trained
    batch = np.array([[0, 0, 0, 1, 0], [1, 2, 1, 0, 1]], dtype=np.float32)
    with pytest.raises(ValueError, match=r"act takes one observation of shape \(5,\)"):
        result.act(batch)
    space = ToyGridEnv().observation_space
    learner = FeedbackLearner(ObsNormalizer.from_space(space), FeedbackConfig(), seed=0)
    policy: HFPolicy = learner.policy
    with pytest.raises(ValueError, match="act takes one observation"):
        policy.act(batch)
    assert policy.act(batch[1]) == int(np.argmax(policy.scores(batch)[1]))


def test_a_truncated_checkpoint_is_a_clear_error_naming_the_file(trained, tmp_path):
    config, _, checkpoint = trained
    data = checkpoint.read_bytes()
    assert load_checkpoint(checkpoint, asdict(config)).state.global_step == 256
    cut = tmp_path / "cut.pt"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"cut\.pt: not a readable checkpoint \(truncated"):
        load_checkpoint(cut, asdict(config))
    with pytest.raises(ValueError, match="not a readable checkpoint"):  # a job resuming it
        train(replace(config), checkpoint_path=cut)


class _Payload:
    """Pickles to a call of ``os.makedirs`` (what a tampered checkpoint could run)."""

    def __init__(self, target: Path) -> None:
        self.target = target

    def __reduce__(self):
        return (os.makedirs, (str(self.target),))


def test_a_checkpoint_carrying_code_is_refused_without_running_it(trained, tmp_path):
    config, _, _ = trained
    target = tmp_path / "ran"
    buffer = io.BytesIO()
    torch.save({"version": 3, "config": asdict(config), "state": _Payload(target)}, buffer)
    evil = tmp_path / "evil.pt"
    evil.write_bytes(buffer.getvalue())
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        load_checkpoint(evil, asdict(config))
    assert not target.exists()
    assert pickle.dumps(_Payload(target))  # the payload itself is a valid pickle
