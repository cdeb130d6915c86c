"""Service-wide routes: the maps sessions can use (``GET /health`` comes with the app)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from starlette.requests import Request

from services.sim.deps import SettingsDep, get_publisher, get_registry, get_settings
from services.sim.lsl_markers import lsl_clock
from services.sim.maps import DEFAULT_MAP_PATH, MapError, load_map
from services.sim.registry import available_maps
from services.sim.schemas import MapPublic

router = APIRouter(tags=["service"])


def health_fields(request: Request) -> dict[str, Any]:
    """The sim's fields of ``GET /health``: load, marker stream and the service's LSL clock."""
    publisher = get_publisher(request)
    return {
        "sessions": len(get_registry(request).list()),
        "max_sessions": get_settings(request).max_sessions,
        "lsl_markers": publisher is not None,
        "marker_stream": publisher.name if publisher is not None else None,
        "lsl_time": lsl_clock(),
    }


@router.get("/maps")
def list_maps(settings: SettingsDep) -> list[MapPublic]:
    """Maps a session can be opened on (pass the name as ``map``), with their descriptions."""
    default = DEFAULT_MAP_PATH.resolve()
    maps = []
    for name, path in available_maps(tuple(settings.extra_map_dirs)).items():
        try:
            description = load_map(path).description
        except MapError as exc:
            description = f"invalid map: {exc}"
        maps.append(MapPublic(name=name, default=path == default, description=description))
    return maps
