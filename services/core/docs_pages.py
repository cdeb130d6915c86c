"""``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) served wholly by the service: their script,
style and icon files come from the ``fastapi-offline`` package and are served under
:data:`DOCS_ASSETS_URL`, so the pages work on a lab network without internet and load
nothing from another host (FastAPI's own pages load them from a CDN).
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

DOCS_ASSETS_URL = "/docs-assets"
"""Where Swagger UI's and ReDoc's files are served."""
ASSETS_DIR = Path(fastapi_offline.__file__).parent / "static"
REDOC_SCRIPT = "redoc.standalone.js"
REDOC_REMOTE_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
"""An image ReDoc's sidebar loads from its maker's CDN; served as this service's icon."""


@cache
def _redoc_script() -> bytes:
    script = (ASSETS_DIR / REDOC_SCRIPT).read_text(encoding="utf-8")
    return script.replace(REDOC_REMOTE_LOGO, f"{DOCS_ASSETS_URL}/favicon.png").encode()


def add_docs_pages(app: FastAPI) -> None:
    """Add ``/docs``, its OAuth2 redirect page, ``/redoc`` and their files to ``app`` (built
    with ``docs_url=None, redoc_url=None``)."""
    openapi_url = app.openapi_url or "/openapi.json"
    redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_swagger_ui_html(
            openapi_url=root + openapi_url,
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=root + redirect_url,
            swagger_js_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png",
            # no badge from the online validator (it would send it this API's address)
            swagger_ui_parameters={"validatorUrl": None, **(app.swagger_ui_parameters or {})},
        )

    @app.get(redirect_url, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_redoc_html(
            openapi_url=root + openapi_url,
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{DOCS_ASSETS_URL}/{REDOC_SCRIPT}",
            redoc_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png",
            with_google_fonts=False,
        )

    @app.get(f"{DOCS_ASSETS_URL}/{REDOC_SCRIPT}", include_in_schema=False)
    async def redoc_script() -> Response:  # before the folder: this copy wins
        return Response(_redoc_script(), media_type="text/javascript; charset=utf-8")

    app.mount(DOCS_ASSETS_URL, StaticFiles(directory=ASSETS_DIR), name="docs-assets")
