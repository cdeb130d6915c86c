"""An online session equals `bgrl reproduce`'s stage 2, and survives restarts bit for bit."""

from __future__ import annotations

from contextlib import closing

import gymnasium as gym
import pytest
import torch

from services.learner.feedback_sources import OracleFeedbackSource
from services.learner.hf_methods import RECOMMENDED_METHOD
from services.learner.runs import learn_hf_policy
from services.learner.seeding import RunSeeds, Stream
from services.learner.specs import RunSpec

SEED = 11
ACCURACY = 0.8
N_LABELS = 48
NOISE_MODEL = {"good_accuracy": ACCURACY, "bad_accuracy": ACCURACY}
"""The session's label-noise model: the simulated feedback's C (as in `bgrl reproduce`)."""


def _env() -> gym.Env:
    config = RunSpec(task="sssg", method="hf_sparse", seed=SEED, accuracy=ACCURACY).ppo_config()
    return gym.make(config.env_id, **config.env_kwargs)


def _online(make_client, data_dir, restart_after: set[int], method: str) -> str:
    """Drive the env with the service's pi_HF and the noisy oracle, restarting the app
    after the given label counts; returns the session id."""
    seeds = RunSeeds(SEED)
    source = OracleFeedbackSource(ACCURACY, seed=seeds.int_seed(Stream.LABEL_NOISE))
    with closing(_env()) as env:
        obs, _ = env.reset(seed=seeds.int_seed(Stream.LABEL_COLLECTION))
        n_labels, step, session_id = 0, 0, None
        while n_labels < N_LABELS:
            with make_client(data_dir=data_dir) as client:
                if session_id is None:
                    created = client.post(
                        "/hf-sessions",
                        json={
                            "seed": SEED,
                            "label_budget": N_LABELS,
                            "fhat": NOISE_MODEL,
                            "method": method,
                        },
                    )
                    session_id = created.json()["id"]
                while n_labels < N_LABELS:
                    answer = client.post(
                        f"/hf-sessions/{session_id}/act", json={"observation": obs.tolist()}
                    ).json()
                    action = answer["action"]
                    optimal = action in env.unwrapped.optimal_actions()
                    next_obs, _, terminated, truncated, _ = env.step(action)
                    correct = source.feedback(obs, action, optimal)
                    response = client.post(
                        f"/hf-sessions/{session_id}/labels",
                        json={
                            "marker_id": f"sim:{step}",
                            "observation": obs.tolist(),
                            "action": action,
                            "feedback": "correct" if correct else "error",
                            "oracle_correct": optimal,
                        },
                    )
                    assert response.status_code == 200, response.text
                    n_labels, step = n_labels + 1, step + 1
                    obs = next_obs
                    if terminated or truncated:
                        obs, _ = env.reset()
                    if n_labels in restart_after:
                        break  # leaves the with-block: the app shuts down
    assert session_id is not None
    return session_id


@pytest.mark.slow
@pytest.mark.parametrize("method", [RECOMMENDED_METHOD, "categorical"])
def test_online_session_equals_offline_collection_across_restarts(make_client, tmp_path, method):
    with closing(_env()) as env:
        offline = learn_hf_policy(env, ACCURACY, SEED, N_LABELS, method=method)

    session_id = _online(make_client, tmp_path, restart_after={1, 17, 30}, method=method)
    with make_client(data_dir=tmp_path) as client:
        public = client.get(f"/hf-sessions/{session_id}").json()
        session = client.app.state.store.get(session_id)
        online_model = session.learner.model.state_dict()
        for name, tensor in offline.model.state_dict().items():
            assert torch.equal(online_model[name], tensor), name
        records = session.labels.records
        assert [(r.correct, r.validation, r.oracle_correct) for r in records] == [
            (r.label, r.validation, r.optimal) for r in offline.records
        ]
        assert [r.observation for r in records] == [r.obs for r in offline.records]
    summary = offline.summary()
    n_validation = sum(r.validation for r in offline.records)
    assert public["labels"] == N_LABELS and public["done"] is True
    assert public["model_version"] == N_LABELS - n_validation
    assert public["metrics"]["validation_accuracy"] == summary["validation_accuracy_noisy"]
    assert public["metrics"]["validation_accuracy_true"] == summary["validation_accuracy_true"]
    assert public["metrics"]["label_accuracy"] == summary["label_accuracy"]


def test_restart_reloads_identical_state(make_client, tmp_path):
    observations = [[float(k + i) % 13 for k in range(10)] + [2.0, 0.5, -0.5] for i in range(25)]
    with make_client(data_dir=tmp_path) as client:
        sid = client.post("/hf-sessions", json={"seed": 4, "label_budget": 100}).json()["id"]
        for i, obs in enumerate(observations):
            action = client.post(f"/hf-sessions/{sid}/act", json={"observation": obs}).json()
            client.post(
                f"/hf-sessions/{sid}/labels",
                json={
                    "marker_id": str(i),
                    "observation": obs,
                    "action": action["action"],
                    "feedback": "error" if i % 3 else "correct",
                    "p_error": 0.75 if i % 3 else 0.25,
                },
            )
        before = client.get(f"/hf-sessions/{sid}").json()
        old = client.app.state.store.get(sid)
        old_state = old.state_dict()
        old_next = [old.act(obs, greedy=False) for obs in observations]  # after the checkpoint
    with make_client(data_dir=tmp_path) as client:
        assert client.get(f"/hf-sessions/{sid}").json() == before
        new = client.app.state.store.get(sid)
        new_state = new.state_dict()
        assert new_state["sampling_rng"] == old_state["sampling_rng"]
        assert new_state["learner"]["rng"] == old_state["learner"]["rng"]
        assert new_state["learner"]["n_updates"] == old_state["learner"]["n_updates"]
        for key in ("model", "buffer"):
            for name, tensor in old_state["learner"][key].items():
                assert torch.equal(new_state["learner"][key][name], tensor), (key, name)
        assert new.learner.optimizer.state_dict()["state"].keys() == (
            old_state["learner"]["optimizer"]["state"].keys()
        )
        for index, slot in old_state["learner"]["optimizer"]["state"].items():
            for name, tensor in slot.items():
                assert torch.equal(new_state["learner"]["optimizer"]["state"][index][name], tensor)
        assert [r.p_error for r in new.labels.records] == [
            0.75 if i % 3 else 0.25 for i in range(25)
        ]
        # the restored generator draws what the old one drew after its last checkpoint
        actions = [
            client.post(f"/hf-sessions/{sid}/act", json={"observation": obs}).json()["action"]
            for obs in observations
        ]
        assert actions == old_next
        # a label re-sent after the restart is not counted twice
        again = client.post(
            f"/hf-sessions/{sid}/labels",
            json={
                "marker_id": "24",
                "observation": observations[24],
                "action": new.labels.get("24").action,
                "feedback": "correct" if 24 % 3 == 0 else "error",
                "p_error": 0.25 if 24 % 3 == 0 else 0.75,
            },
        ).json()
        assert again["duplicate"] is True and again["labels"] == 25


def test_a_soft_session_takes_likelihood_ratios_and_survives_a_restart(make_client, tmp_path):
    """On the soft channel a label needs its log-likelihood ratio (422 naming it without);
    the ratio is journaled, so a restart replays the same soft updates, and a soft label is
    never prepared (its update needs the ratio)."""
    observations = [[float(k + i) % 13 for k in range(10)] + [2.0, 0.5, -0.5] for i in range(12)]
    with make_client(data_dir=tmp_path) as client:
        sid = client.post(
            "/hf-sessions",
            json={"seed": 4, "label_budget": 50, "fhat": {"label_channel": "soft"}},
        ).json()["id"]
        label = {"marker_id": "x", "observation": observations[0], "action": 0}
        refused = client.post(f"/hf-sessions/{sid}/labels", json={**label, "feedback": "error"})
        assert refused.status_code == 422 and "log_likelihood_ratio" in refused.text
        prepared = client.post(f"/hf-sessions/{sid}/labels/prepare", json=label).json()
        assert prepared == {"prepared": False}
        for i, obs in enumerate(observations):
            action = client.post(f"/hf-sessions/{sid}/act", json={"observation": obs}).json()
            response = client.post(
                f"/hf-sessions/{sid}/labels",
                json={
                    "marker_id": str(i),
                    "observation": obs,
                    "action": action["action"],
                    "feedback": "error" if i % 3 else "correct",
                    "log_likelihood_ratio": 0.8 if i % 3 else -0.5,
                },
            )
            assert response.status_code == 200, response.text
        old = client.app.state.store.get(sid)
        weights = {k: v.clone() for k, v in old.learner.model.state_dict().items()}
        assert old.labels.records[-1].log_likelihood_ratio == 0.8
    with make_client(data_dir=tmp_path) as client:
        new = client.app.state.store.get(sid)
        assert new.learner.soft and len(new.labels) == len(observations)
        for name, tensor in weights.items():
            assert torch.equal(new.learner.model.state_dict()[name], tensor), name
