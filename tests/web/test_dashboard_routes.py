"""The dashboard's routes without a browser: pages, assets, the Content-Security-Policy."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from services.api.routes.dashboard import CONTENT_SECURITY_POLICY, WEB_DIR
from tests.api.conftest import make_settings


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    tmp_path = tmp_path_factory.mktemp("dashboard")
    settings = make_settings(tmp_path / "data", f"sqlite:///{tmp_path / 'bgrl.db'}")
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.mark.parametrize(
    "path", ["/", "/signin", "/subjects", "/subjects/12", "/sessions", "/jobs", "/jobs/ab12",
             "/models", "/classifiers/3", "/recordings", "/account", "/admin/users",
             "/admin/rigs", "/admin/audit"],
)  # fmt: skip
def test_every_page_path_serves_the_dashboard(client: TestClient, path: str) -> None:
    response = client.get(path)
    assert response.status_code == 200
    assert response.headers["content-type"] == "text/html; charset=utf-8"
    assert response.text == (WEB_DIR / "index.html").read_text()
    assert response.headers["content-security-policy"] == CONTENT_SECURITY_POLICY
    assert response.headers["x-content-type-options"] == "nosniff"


def test_the_start_page_links_the_api_docs(client: TestClient) -> None:
    text = client.get("/").text
    assert 'href="/docs"' in text
    for label in ("Subjects", "Sessions", "Jobs", "Models"):
        assert f">{label}</a>" in text


def test_policy_allows_this_host_only() -> None:
    directives = dict(d.split(" ", 1) for d in CONTENT_SECURITY_POLICY.split("; "))
    assert directives["default-src"] == "'none'"
    assert directives["script-src"] == "'self'"
    assert directives["connect-src"] == "'self'"
    assert directives["frame-ancestors"] == "'none'"
    assert all("http" not in value and "*" not in value for value in directives.values())


def test_assets_are_served_with_their_types(client: TestClient) -> None:
    script = client.get("/assets/js/app.js")
    assert script.status_code == 200
    assert script.headers["content-type"] == "text/javascript; charset=utf-8"
    assert script.headers["content-security-policy"] == CONTENT_SECURITY_POLICY
    assert client.get("/assets/app.css").headers["content-type"] == "text/css; charset=utf-8"
    assert client.get("/assets/icon.svg").headers["content-type"] == "image/svg+xml"


@pytest.mark.parametrize(
    "path", ["/assets/../pyproject.toml", "/assets/%2e%2e/services/api/app.py",
             "/assets/js/missing.js", "/assets/js", "/assets/index.txt"],
)  # fmt: skip
def test_nothing_outside_web_or_unknown_is_served(client: TestClient, path: str) -> None:
    response = client.get(path)
    assert response.status_code == 404
    assert "[project]" not in response.text and "import" not in response.text


def test_no_asset_refers_to_another_host() -> None:
    for path in WEB_DIR.rglob("*"):
        if path.suffix in (".html", ".js", ".css"):
            text = path.read_text().replace("http://www.w3.org/2000/svg", "")  # a name only
            assert "http://" not in text and "https://" not in text and "//cdn" not in text, path
