"""Service-wide routes: health and the maps sessions can use."""

from __future__ import annotations

from fastapi import APIRouter

from services.sim.deps import PublisherDep, RegistryDep, SettingsDep
from services.sim.lsl_markers import lsl_clock
from services.sim.maps import DEFAULT_MAP_PATH
from services.sim.schemas import HealthPublic, MapPublic
from services.sim.sessions import available_maps

router = APIRouter(tags=["service"])


@router.get("/health")
def health(registry: RegistryDep, publisher: PublisherDep, settings: SettingsDep) -> HealthPublic:
    """Liveness, open sessions and whether action markers are published on LSL."""
    return HealthPublic(
        status="ok",
        sessions=len(registry.list()),
        max_sessions=settings.max_sessions,
        lsl_markers=publisher is not None,
        marker_stream=publisher.name if publisher is not None else None,
        lsl_time=lsl_clock(),
    )


@router.get("/maps")
def list_maps(settings: SettingsDep) -> list[MapPublic]:
    """Maps a session can be opened on (pass the name as ``map``)."""
    maps = available_maps(tuple(settings.extra_map_dirs))
    default = DEFAULT_MAP_PATH.resolve()
    return [MapPublic(name=name, default=path == default) for name, path in maps.items()]
