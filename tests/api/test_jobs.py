"""Jobs from the api's side: the row is committed, then the task is on the real broker."""

from __future__ import annotations

import hashlib
from typing import Any

import pytest
from starlette.websockets import WebSocketDisconnect

from services.core.db.models import Artifact, Job
from services.core.queue import JOB_QUEUE
from services.platform.jobs import GUIDED_PPO, JOB_KINDS, SUBMITTED_KINDS
from tests.api.conftest import Api, calibration_session

GUIDED = {"task": "SSSG", "method": "hf_sparse", "accuracy": 0.7, "seed": 3, "total_steps": 2048}


def broker_messages(api: Api) -> list[tuple[str, list[Any]]]:
    """(task name, args) of every message waiting on the jobs queue (consumed)."""
    messages = []
    celery = api.client.app.state.celery
    with celery.connection_for_read() as connection:
        queue = connection.SimpleQueue(JOB_QUEUE)
        try:
            while True:
                try:
                    message = queue.get(timeout=0.5)
                except queue.Empty:
                    break
                args = message.decode()[0]
                messages.append((message.headers["task"], args))
                message.ack()
        finally:
            queue.close()
    return messages


def submit(api: Api, kind: str, config: dict[str, Any], role: str = "staff"):
    return api.client.post(
        "/api/v1/jobs", json={"kind": kind, "config": config}, headers=api.as_(role)
    )


def set_job(api: Api, job_id: str, **values: Any) -> None:
    """Change a job's row as a worker would."""
    with api.client.app.state.sessions() as db:
        job = db.get(Job, job_id)
        for key, value in values.items():
            setattr(job, key, value)
        db.commit()


def test_submit_commits_the_row_then_enqueues_it(api_any_db: Api) -> None:
    api = api_any_db
    response = submit(
        api, "guided_ppo", {**GUIDED, "ppo": {"n_epochs": 10, "hidden_sizes": [32, 32]}}
    )
    assert response.status_code == 201, response.text
    job = response.json()
    assert (job["status"], job["progress"], job["attempts"]) == ("queued", 0.0, 0)
    assert job["config"] == {
        "task": "sssg",
        "method": "hf_sparse",
        "accuracy": 0.7,
        "seed": 3,
        "total_steps": 2048,
        "hf_treatment": "authors",
        "ppo": {"n_epochs": 10, "hidden_sizes": [32, 32]},
        "preset": "paper",
        "n_labels": 1000,
    }
    with api.client.app.state.sessions() as db:
        row = db.get(Job, job["id"])
        assert (row.status, row.kind, row.submitter_id) == (
            "queued",
            "guided_ppo",
            api.user_ids["staff"],
        )
    assert broker_messages(api) == [("bgrl.jobs.guided_ppo", [job["id"]])]
    fetched = api.client.get(f"/api/v1/jobs/{job['id']}", headers=api.as_("viewer")).json()
    assert fetched == job


@pytest.mark.parametrize(
    ("config", "field"),
    [
        ({"task": "SSSG", "method": "hf_sparse"}, "config"),
        ({"task": "XXL", "method": "rl_sparse"}, "config.task"),
        ({"task": "SSSG", "method": "rl_sparse", "accuracy": 0.6}, "config"),
        ({"task": "SSSG", "method": "rl_sparse", "colour": "red"}, "config.colour"),
        ({"task": "SSSG", "method": "rl_sparse", "ppo": {"bogus": 1}}, "config.ppo.bogus"),
        ({"task": "SSSG", "method": "rl_sparse", "ppo": {"seed": 1}}, "config.ppo.seed"),
        ({"task": "SSSG", "method": "rl_sparse", "ppo": {"n_steps": 100}}, "config"),
        ({"task": "SSSG", "method": "rl_sparse", "ppo": {"total_steps": 10}}, "config"),
        ({"task": "SSSG", "method": "rl_sparse", "total_steps": 0}, "config.total_steps"),
        (
            {"task": "SSSG", "method": "rl_sparse", "ppo": {"learning_rate": "fast"}},
            "config.ppo.learning_rate",
        ),
        ({"task": "SSSG", "method": "rl_sparse", "hf_method": "paper"}, "config.hf_method"),
        (
            {"task": "SSSG", "method": "hf_sparse", "accuracy": 0.7, "hf_method": "best"},
            "config.hf_method",
        ),
        (
            {"task": "SSSG", "method": "hf_sparse", "hf_model_id": 1, "hf_method": "paper"},
            "config.hf_method",
        ),
    ],
)
def test_guided_ppo_config_is_checked_field_by_field(api: Api, config: dict, field: str) -> None:
    response = submit(api, "guided_ppo", config)
    assert response.status_code == 422, response.text
    assert response.json()["detail"][0]["field"] == field
    assert broker_messages(api) == []


def test_hf_method_is_taken_for_hf_sparse_and_refused_for_the_others(api: Api) -> None:
    response = submit(api, "guided_ppo", {**GUIDED, "hf_method": "thompson"})
    assert response.status_code == 201, response.text
    assert response.json()["config"]["hf_method"] == "thompson"
    default = submit(api, "guided_ppo", GUIDED).json()
    assert "hf_method" not in default["config"]  # the worker uses the recommended method
    refused = submit(api, "guided_ppo", {"task": "VSSG", "method": "rl_rich", "hf_method": "paper"})
    assert refused.status_code == 422
    assert refused.json()["detail"][0]["field"] == "config.hf_method"
    assert refused.json()["message"] == (
        "config.hf_method: hf_method applies to hf_sparse only, not rl_rich"
    )
    assert broker_messages(api) == [
        ("bgrl.jobs.guided_ppo", [response.json()["id"]]),
        ("bgrl.jobs.guided_ppo", [default["id"]]),
    ]


def test_ppo_step_rule_is_explained(api: Api) -> None:
    response = submit(
        api, "guided_ppo", {"task": "SSSG", "method": "rl_sparse", "ppo": {"n_steps": 100}}
    )
    assert response.json()["message"] == (
        "config: n_steps (100) must be a multiple of minibatch_size (64)"
    )


def test_bad_job_requests_are_4xx_never_5xx(api: Api) -> None:
    nan = api.client.post(
        "/api/v1/jobs",
        content=b'{"kind": "guided_ppo", "config": '
        b'{"task": "SSSG", "method": "hf_sparse", "accuracy": NaN}}',
        headers={**api.as_("staff"), "content-type": "application/json"},
    )
    assert nan.status_code == 422
    assert nan.json()["detail"][0]["field"] == "config.accuracy"
    child = submit(api, "reproduce_run", {})
    assert child.status_code == 422
    assert child.json()["detail"][0]["field"] == "kind"
    missing = submit(api, "eeg_calibration", {"recording_id": 42})
    assert missing.status_code == 422
    assert missing.json() == {"detail": "no recording with id 42", "field": "config.recording_id"}
    hf = submit(api, "guided_ppo", {"task": "VSSG", "method": "hf_sparse", "hf_model_id": 7})
    assert hf.json() == {"detail": "no HF model with id 7", "field": "config.hf_model_id"}
    huge = submit(api, "reproduce", {"seeds": 100, "accuracies": [0.1 * i for i in range(1, 10)]})
    assert huge.status_code == 422
    assert huge.json()["detail"][0]["msg"].endswith("runs; a reproduce job may have 2000")
    body = api.client.post(
        "/api/v1/jobs",
        content=b'{"kind": "reproduce", "config": {"quick": true, "x": "'
        + b"a" * 2_000_000
        + b'"}}',
        headers={**api.as_("staff"), "content-type": "application/json"},
    )
    assert body.status_code == 413
    assert body.json()["field"] == "body"
    assert submit(api, "guided_ppo", GUIDED, role="viewer").status_code == 403


def test_reproduce_config_takes_the_cli_options(api: Api) -> None:
    response = submit(
        api,
        "reproduce",
        {
            "quick": True,
            "tasks": ["VSSG"],
            "methods": ["rl_sparse", "hf_sparse"],
            "accuracies": [0.6],
            "treatments": ["truncated_is"],
            "ppo": {"hf_guide_sampling": True},
        },
    )
    assert response.status_code == 201, response.text
    assert response.json()["config"] == {
        "quick": True,
        "seeds": 2,
        "first_seed": 0,
        "tasks": ["vssg"],
        "methods": ["rl_sparse", "hf_sparse"],
        "accuracies": [0.6],
        "treatments": ["truncated_is"],
        "ppo": {"hf_guide_sampling": True},
        "preset": "paper",
        "n_labels": 1000,
        "batch_runs": 8,
    }
    assert broker_messages(api) == [("bgrl.jobs.reproduce", [response.json()["id"]])]
    platform = submit(api, "reproduce", {"quick": True, "preset": "platform"})
    assert platform.status_code == 201, platform.text
    assert platform.json()["config"]["preset"] == "platform"
    assert (
        submit(api, "reproduce", {"quick": True, "n_labels": 4000}).json()["config"]["n_labels"]
        == 4000
    )
    no_labels = submit(api, "reproduce", {"quick": True, "n_labels": 0})
    assert no_labels.status_code == 422
    assert no_labels.json()["detail"][0]["field"] == "config.n_labels"
    unknown = submit(api, "reproduce", {"quick": True, "preset": "lab"})
    assert unknown.status_code == 422
    assert unknown.json()["detail"][0]["field"] == "config.preset"
    single = submit(api, "reproduce", {"quick": True, "batch_runs": 1})
    assert single.json()["config"]["batch_runs"] == 1
    for too_many in (0, 33):
        refused = submit(api, "reproduce", {"quick": True, "batch_runs": too_many})
        assert refused.status_code == 422
        assert refused.json()["detail"][0]["field"] == "config.batch_runs"


def test_list_filters_and_pages(api: Api) -> None:
    ids = [submit(api, "guided_ppo", {**GUIDED, "seed": s}).json()["id"] for s in range(3)]
    other = submit(api, "reproduce", {"quick": True}, role="admin").json()["id"]
    set_job(api, ids[0], status="succeeded")
    viewer = api.as_("viewer")
    page = api.client.get("/api/v1/jobs?kind=guided_ppo&limit=2", headers=viewer).json()
    assert (page["total"], len(page["items"]), page["limit"]) == (3, 2, 2)
    assert [j["id"] for j in page["items"]] == [ids[2], ids[1]]
    second = api.client.get("/api/v1/jobs?kind=guided_ppo&limit=2&offset=2", headers=viewer).json()
    assert [j["id"] for j in second["items"]] == [ids[0]]
    done = api.client.get("/api/v1/jobs?status=succeeded", headers=viewer).json()
    assert [j["id"] for j in done["items"]] == [ids[0]]
    mine = api.client.get(
        f"/api/v1/jobs?submitter_id={api.user_ids['admin']}", headers=viewer
    ).json()
    assert [j["id"] for j in mine["items"]] == [other]
    bad = api.client.get("/api/v1/jobs?status=exploded", headers=viewer)
    assert bad.status_code == 422
    assert bad.json()["detail"][0]["field"] == "status"


def test_cancel_and_retry(api: Api) -> None:
    staff = api.as_("staff")
    queued = submit(api, "guided_ppo", GUIDED).json()["id"]
    running = submit(api, "guided_ppo", {**GUIDED, "seed": 4}).json()["id"]
    broker_messages(api)
    set_job(api, running, status="running")
    cancelled = api.client.post(f"/api/v1/jobs/{queued}/cancel", headers=staff).json()
    assert (cancelled["status"], cancelled["cancel_requested"]) == ("cancelled", True)
    assert cancelled["finished_at"] is not None
    asked = api.client.post(f"/api/v1/jobs/{running}/cancel", headers=staff).json()
    assert (asked["status"], asked["cancel_requested"]) == ("running", True)
    twice = api.client.post(f"/api/v1/jobs/{queued}/cancel", headers=staff)
    assert twice.status_code == 409
    assert twice.json() == {"detail": f"job {queued} is already cancelled", "field": "job_id"}
    not_yet = api.client.post(f"/api/v1/jobs/{running}/retry", headers=staff)
    assert not_yet.status_code == 409
    set_job(api, running, status="failed", error="worker lost", attempts=3)
    retried = api.client.post(f"/api/v1/jobs/{running}/retry", headers=staff).json()
    assert (retried["status"], retried["error"], retried["attempts"]) == ("queued", None, 0)
    assert retried["cancel_requested"] is False
    assert broker_messages(api) == [("bgrl.jobs.guided_ppo", [running])]
    unknown = api.client.post("/api/v1/jobs/nope/cancel", headers=staff)
    assert unknown.status_code == 404
    assert unknown.json() == {"detail": "no job with id nope", "field": "job_id"}


def test_cancel_of_a_queued_live_session_ends_its_run_and_says_who(api: Api) -> None:
    staff = api.as_("staff")
    session_id = calibration_session(api)
    started = api.client.post(
        f"/api/v1/sessions/{session_id}/start", json={"accelerated": True}, headers=staff
    )
    assert started.status_code == 201, started.text
    job_id = started.json()["job_id"]
    cancelled = api.client.post(f"/api/v1/jobs/{job_id}/cancel", headers=staff).json()
    assert cancelled["status"] == "cancelled"
    live = api.client.get(f"/api/v1/sessions/{session_id}/live", headers=staff).json()
    assert live["run"]["status"] == "failed"
    assert live["run"]["error"] == (
        "session ended after 0 steps: cancelled by staff@lab.test; its markers, decisions "
        "and labels are kept, start the session again to resume"
    )
    session = api.client.get(f"/api/v1/sessions/{session_id}", headers=staff).json()
    assert session["status"] == "failed"
    again = api.client.post(
        f"/api/v1/sessions/{session_id}/start", json={"accelerated": True}, headers=staff
    )
    assert again.status_code == 201, again.text  # it resumes from its rows
    assert again.json()["id"] == live["run"]["id"]


def test_curve_plot_and_model(api: Api) -> None:
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    viewer = api.as_("viewer")
    empty_plot = api.client.get(f"/api/v1/jobs/{job_id}/plot.png", headers=viewer)
    assert empty_plot.status_code == 404
    no_model = api.client.get(f"/api/v1/jobs/{job_id}/model", headers=viewer)
    assert no_model.status_code == 404
    assert no_model.json() == {
        "detail": f"job {job_id} (queued) has no model yet",
        "field": "job_id",
    }
    store = api.client.app.state.store
    policy = b"torchscript policy bytes"
    stored = store.put_bytes(policy, kind="model", name="policy.pt")
    with api.client.app.state.sessions() as db:
        db.add(
            Artifact(
                id="m" * 32,
                kind="model",
                relpath=stored.relpath,
                sha256=stored.sha256,
                size_bytes=stored.size_bytes,
                job_id=job_id,
            )
        )
        db.commit()
    set_job(
        api, job_id, curve=[[0, 0.0], [2048, 0.5]], model_artifact_id="m" * 32, status="succeeded"
    )
    curve = api.client.get(f"/api/v1/jobs/{job_id}/curve", headers=viewer)
    assert curve.json() == {"job_id": job_id, "curve": [[0, 0.0], [2048, 0.5]]}
    csv = api.client.get(f"/api/v1/jobs/{job_id}/curve?format=csv", headers=viewer)
    assert csv.headers["content-type"].startswith("text/csv")
    assert csv.text == "step,spl\n0,0.0\n2048,0.5\n"
    plot = api.client.get(f"/api/v1/jobs/{job_id}/plot.png", headers=viewer)
    assert plot.headers["content-type"] == "image/png"
    assert plot.content[:8] == b"\x89PNG\r\n\x1a\n"
    model = api.client.get(f"/api/v1/jobs/{job_id}/model", headers=viewer)
    assert model.content == policy
    assert model.headers["x-checksum-sha256"] == hashlib.sha256(policy).hexdigest()
    artifact = api.client.get(f"/api/v1/artifacts/{'m' * 32}/download", headers=viewer)
    assert artifact.content == policy
    listed = api.client.get(f"/api/v1/artifacts?job_id={job_id}", headers=viewer).json()
    assert [a["sha256"] for a in listed["items"]] == [hashlib.sha256(policy).hexdigest()]


def _token(api: Api, role: str) -> str:
    return api.as_(role)["Authorization"].split(" ", 1)[1]


def test_progress_websocket(api: Api) -> None:
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    url = f"/api/v1/jobs/{job_id}/events"
    protocols = ["bgrl", f"bearer.{_token(api, 'viewer')}"]  # as a browser sends it
    with api.client.websocket_connect(url, subprotocols=protocols) as ws:
        assert ws.accepted_subprotocol == "bgrl"  # never the token
        first = ws.receive_json()
        assert (first["id"], first["status"]) == (job_id, "queued")
        set_job(api, job_id, status="running", progress=0.5, steps_done=1024)
        second = ws.receive_json()
        assert (second["status"], second["progress"], second["steps_done"]) == (
            "running",
            0.5,
            1024,
        )
        set_job(api, job_id, status="succeeded", progress=1.0)
        assert ws.receive_json()["status"] == "succeeded"
        with pytest.raises(WebSocketDisconnect) as closed:
            ws.receive_json()
        assert closed.value.code == 1000


@pytest.mark.parametrize(
    ("query", "protocols", "headers", "code"),
    [
        ("", [], {}, 4401),
        ("", ["bgrl", "bearer.garbage"], {}, 4401),
        ("?token={viewer}", [], {}, 4401),  # a token in the URL is refused: URLs are logged
        ("", ["bgrl", "bearer.{viewer}"], {"origin": "https://evil.example"}, 4403),
    ],
)
def test_progress_websocket_refuses_before_accept(
    api: Api, query: str, protocols: list[str], headers: dict, code: int
) -> None:
    job_id = submit(api, "guided_ppo", GUIDED).json()["id"]
    viewer = _token(api, "viewer")
    url = f"/api/v1/jobs/{job_id}/events" + query.format(viewer=viewer)
    offered = [protocol.format(viewer=viewer) for protocol in protocols]
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        api.client.websocket_connect(url, subprotocols=offered, headers=headers),
    ):
        pass
    assert refused.value.code == code


def test_progress_websocket_unknown_job_and_header_auth(api: Api) -> None:
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        api.client.websocket_connect("/api/v1/jobs/nope/events", headers=api.as_("viewer")),
    ):
        pass
    assert refused.value.code == 4404


def test_the_form_hints_of_the_schemas_name_real_fields_and_lists(api: Api) -> None:
    """What the dashboard's generated job form relies on: each ``x-shown-when`` names sibling
    fields and values they can hold, each ``x-references`` a list route of the api."""
    viewer = api.as_("viewer")
    kinds = api.client.get("/api/v1/job-kinds", headers=viewer).json()
    shown_when, references = 0, set()
    for kind in kinds:
        schema = kind["config_schema"]
        if schema is None:
            continue
        objects = [schema, *schema.get("$defs", {}).values()]
        for obj in objects:
            for prop in obj["properties"].values():
                for name, values in prop.get("x-shown-when", {}).items():
                    sibling = obj["properties"][name]
                    allowed = sibling.get("enum") or [
                        v for s in sibling.get("anyOf", []) for v in s.get("enum", [None])
                    ]
                    assert set(values) <= {*allowed, None}, (kind["name"], name, values)
                    shown_when += 1
                if "x-references" in prop:
                    references.add(prop["x-references"])
    assert shown_when >= 5
    assert references == {"hf-models", "recordings", "subjects", "classifiers"}
    for collection in references:
        listed = api.client.get(f"/api/v1/{collection}", headers=viewer)
        assert listed.status_code == 200 and "items" in listed.json(), collection


def test_job_kinds_give_each_kinds_config_schema(api: Api) -> None:
    """The registry's kinds with the JSON Schema the api validates with: a job built from the
    schema's required fields and bounds is accepted, one past a bound is refused."""
    assert api.client.get("/api/v1/job-kinds").status_code == 401
    kinds = {
        k["name"]: k for k in api.client.get("/api/v1/job-kinds", headers=api.as_("viewer")).json()
    }
    assert list(kinds) == list(JOB_KINDS)
    assert {k for k, v in kinds.items() if v["submittable"]} == set(SUBMITTED_KINDS)
    guided = kinds[GUIDED_PPO.name]
    assert guided["counts_steps"] and guided["title"] == GUIDED_PPO.title
    schema = guided["config_schema"]
    assert set(schema["required"]) == {"task", "method"}
    n_epochs = schema["$defs"]["PPOOverrides"]["properties"]["n_epochs"]["anyOf"][0]
    assert (n_epochs["minimum"], n_epochs["maximum"]) == (1, 1000)
    assert kinds["live_session"]["config_schema"] is None
    config = {"task": "sssg", "method": "rl_sparse", "ppo": {"n_epochs": 1000}}
    assert submit(api, GUIDED_PPO.name, config).status_code == 201
    config["ppo"]["n_epochs"] = 1001
    refused = submit(api, GUIDED_PPO.name, config)
    assert refused.status_code == 422
    assert refused.json()["detail"][0]["field"] == "config.ppo.n_epochs"
