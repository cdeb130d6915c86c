"""Still images of a session: the top-down map with the trajectory and single frames."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from services.sim.deps import SessionDep, SettingsDep
from services.sim.imaging import MEDIA_TYPES, encode_image
from services.sim.schemas import FrameFormat
from services.sim.sessions import FrameView

router = APIRouter(prefix="/sessions/{session_id}", tags=["images"])


@router.get("/map.png", response_class=Response, responses={200: {"content": {"image/png": {}}}})
def map_png(session: SessionDep) -> Response:
    """Top-down map (obstacles, goal, robot) with the current episode's trajectory, as PNG."""
    image = session.render_frame("topdown")
    return Response(encode_image(image, "png"), media_type=MEDIA_TYPES["png"])


@router.get(
    "/frame",
    response_class=Response,
    responses={200: {"content": {"image/jpeg": {}, "image/png": {}}}},
)
def frame(
    session: SessionDep,
    settings: SettingsDep,
    view: Annotated[FrameView, Query()] = "camera",
    image_format: Annotated[FrameFormat, Query(alias="format")] = "jpeg",
) -> Response:
    """One frame: the third-person camera (configured frame size) or the top-down map."""
    image = session.render_frame(view)
    body = encode_image(image, image_format, jpeg_quality=settings.jpeg_quality)
    return Response(body, media_type=MEDIA_TYPES[image_format])
