"""The web dashboard: the static pages and scripts of ``web/`` (no authentication here: the
pages sign in through ``POST /api/v1/auth/token`` and call the API with the token).

Every page path answers with ``web/index.html`` (the page script shows the right view);
``/assets/...`` serves the rest of ``web/``. Responses carry a Content-Security-Policy that
allows this host only: no CDN, no remote fonts, no inline scripts, no framing.
"""

from __future__ import annotations

import logging
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

from services.core.errors import NotFoundError

log = logging.getLogger(__name__)
router = APIRouter(include_in_schema=False)

WEB_DIR = Path(__file__).resolve().parents[3] / "web"
"""The dashboard's assets: ``web/`` at the repository root (beside ``services/``)."""

CONTENT_SECURITY_POLICY = "; ".join(
    (
        "default-src 'none'",
        "script-src 'self'",
        "style-src 'self'",
        "img-src 'self' blob: data:",
        "connect-src 'self'",
        "font-src 'self'",
        "manifest-src 'self'",
        "form-action 'self'",
        "base-uri 'none'",
        "frame-ancestors 'none'",
        "object-src 'none'",
    )
)
"""Only this host (``'self'`` covers its websockets); ``blob:`` images are the plots the
pages fetch with the token."""

SECURITY_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-cache",
}
MEDIA_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".ico": "image/x-icon",
}
PAGES = (
    "/",
    "/signin",
    "/subjects",
    "/sessions",
    "/jobs",
    "/models",
    "/recordings",
    "/account",
    "/admin/users",
    "/admin/rigs",
    "/admin/audit",
)
"""Paths answered with the dashboard (and ``/subjects/{id}``, ``/jobs/{id}``,
``/classifiers/{id}``)."""


def _file(path: Path) -> FileResponse:
    if not path.is_file():
        log.error("dashboard file %s is missing (web/ must sit beside services/)", path)
        raise NotFoundError(f"dashboard file {path.name} is not installed", field="path")
    return FileResponse(path, media_type=MEDIA_TYPES[path.suffix], headers=SECURITY_HEADERS)


def index() -> FileResponse:
    """The dashboard page (the script shows the view the path names)."""
    return _file(WEB_DIR / "index.html")


for _page in PAGES:
    router.add_api_route(_page, index, methods=["GET"])


@router.get("/sessions/{session_id}/live")
@router.get("/sessions/{session_id}/display")
@router.get("/subjects/{subject_id}")
@router.get("/jobs/{job_id}")
@router.get("/classifiers/{classifier_id}")
def item_page() -> FileResponse:
    """A subject's, job's or classifier's page."""
    return index()


@router.get("/assets/{asset_path:path}")
def asset(asset_path: str) -> FileResponse:
    """A script, style sheet or icon of ``web/`` (nothing outside it, known types only)."""
    root = WEB_DIR.resolve()
    path = (root / asset_path).resolve()
    if not path.is_relative_to(root) or path.suffix not in MEDIA_TYPES:
        raise NotFoundError(f"no dashboard asset {asset_path!r}", field="path")
    if not path.is_file():
        raise NotFoundError(f"no dashboard asset {asset_path!r}", field="path")
    return _file(path)
