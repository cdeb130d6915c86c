"""The API's /docs and /redoc work without internet: Swagger UI and ReDoc are served by the
platform itself (the dashboard's no-CDN rule, applied to them too)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from services.api.app import create_app
from tests.api.conftest import make_settings
from tests.web.conftest import Server

ASSET = re.compile(r"""(?:src|href)\s*=\s*["']([^"']+)["']|url\s*:\s*["']([^"']+)["']""")


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    root: Path = tmp_path_factory.mktemp("docs")
    settings = make_settings(root / "data", f"sqlite:///{root / 'bgrl.db'}")
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_load_everything_from_this_host(client: TestClient, page: str) -> None:
    html = client.get(page)
    assert html.status_code == 200
    refs = [a or b for a, b in ASSET.findall(html.text)]
    assert refs, html.text
    for ref in refs:
        assert not ref.startswith(("http:", "https:", "//")), (page, ref)
        asset = client.get(ref)
        assert asset.status_code == 200, (page, ref)
    assert "fonts.googleapis" not in html.text
    scripts = [client.get(ref).content for ref in refs if ref.endswith(".js")]
    assert scripts and all(len(script) > 100_000 for script in scripts)
    assert not any(b"https://cdn." in script for script in scripts)  # ReDoc's logo
    if page == "/docs":
        assert '"validatorUrl": null' in html.text  # no badge from validator.swagger.io


@pytest.mark.slow
@pytest.mark.parametrize(
    ("page", "shown"),
    [("/docs", ".swagger-ui .info .title"), ("/redoc", ".redoc-wrap h1")],
)
def test_docs_pages_render_in_a_browser_without_internet(
    context: tuple, server: Server, page: str, shown: str
) -> None:
    """Chromium, every request off 127.0.0.1 refused by the ``context`` fixture."""
    ctx, watch = context
    tab = ctx.new_page()
    tab.goto(page)
    title = tab.locator(shown).first
    title.wait_for(timeout=60_000)
    assert "Brain-guided RL platform API" in title.inner_text()
    assert watch.errors_except() == []
