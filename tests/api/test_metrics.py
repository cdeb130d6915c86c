"""``GET /metrics`` (Prometheus): admins and the internal token only; request latency by
route template, jobs by status, queue depth and the live decision latency on the api; the
request histograms on every service."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from services.core.db.models import Job
from services.sim.app import create_app as create_sim_app
from services.sim.settings import SimSettings
from tests.api.conftest import Api, make_settings, start_api

TOKEN = "metrics-test-token-0123456789"


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def test_api_metrics_for_admins_and_the_internal_token(tmp_path: Path) -> None:
    for api in start_api(make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'b.db'}",
                                       service_token=TOKEN)):  # fmt: skip
        client = api.client
        with client.app.state.sessions() as db:
            db.add_all([Job(kind="guided_ppo", config={}, status=s) for s in
                        ("queued", "queued", "running", "succeeded")])  # fmt: skip
            db.commit()
        for job_id in ("abc", "def"):  # two ids, one route template
            client.get(f"/api/v1/jobs/{job_id}", headers=api.as_("viewer"))
        for role in ("viewer", "staff"):
            refused = client.get("/metrics", headers=api.as_(role))
            assert refused.status_code == 403 and refused.json()["field"] == "role"
        anonymous = client.get("/metrics")
        assert anonymous.status_code == 403 and anonymous.json()["field"] == "x-service-token"
        wrong = client.get("/metrics", headers={"X-Service-Token": "wrong"})
        assert wrong.status_code == 403
        for headers in (api.as_("admin"), {"X-Service-Token": TOKEN}):
            response = client.get("/metrics", headers=headers)
            assert response.status_code == 200, response.text
            assert response.headers["content-type"].startswith("text/plain")
            found = samples(response.text)
            assert found[("bgrl_jobs", (("status", "queued"),))] == 2
            assert found[("bgrl_jobs", (("status", "failed"),))] == 0
            assert found[("bgrl_job_queue_depth", ())] == 2
            assert found[("bgrl_live_decision_latency_seconds_count", ())] == 0
            route = (("method", "GET"), ("route", "/api/v1/jobs/{job_id}"), ("status", "404"))
            assert found[("bgrl_http_request_duration_seconds_count", route)] == 2
            assert found[("target_info", (("service", "api"),))] == 1


def test_a_service_serves_metrics_to_the_internal_token_only(tmp_path: Path) -> None:
    settings = SimSettings(data_dir=tmp_path, service_token=TOKEN, lsl_markers=False)
    with TestClient(create_sim_app(settings)) as client:
        assert client.get("/health").status_code == 200
        assert client.get("/metrics").status_code == 401  # the service's token check
        response = client.get("/metrics", headers={"X-Service-Token": TOKEN})
        assert response.status_code == 200
        found = samples(response.text)
        health = (("method", "GET"), ("route", "/health"), ("status", "200"))
        assert found[("bgrl_http_request_duration_seconds_count", health)] == 1
        assert found[("target_info", (("service", "sim"),))] == 1
    without_token = SimSettings(data_dir=tmp_path, service_token=None, lsl_markers=False)
    with TestClient(create_sim_app(without_token)) as client:
        refused = client.get("/metrics")
        assert refused.status_code == 403  # no token configured: metrics are not public


def test_no_metrics_without_a_token_or_an_admin(api: Api) -> None:
    assert api.client.get("/metrics").status_code == 403
    assert api.client.get("/metrics", headers=api.as_("admin")).status_code == 200
