"""The oracle: optimal actions and cost-to-go at the robot's pose or any pose."""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, Query

from services.sim.deps import SessionDep
from services.sim.errors import BadQueryError
from services.sim.schemas import OraclePublic

router = APIRouter(prefix="/sessions/{session_id}/oracle", tags=["oracle"])

MAX_ABS_YAW = 2.0 * math.pi
"""Largest ``|yaw|`` accepted (rad); the service itself reports yaw in [-pi, pi)."""

Coordinate = Annotated[
    float | None, Query(allow_inf_nan=False, description="Metres, within the map's floor.")
]
Yaw = Annotated[
    float | None,
    Query(allow_inf_nan=False, ge=-MAX_ABS_YAW, le=MAX_ABS_YAW, description="Radians."),
]


@router.get("")
def query_oracle(
    session: SessionDep, x: Coordinate = None, y: Coordinate = None, yaw: Yaw = None
) -> OraclePublic:
    """Optimal actions and cost-to-go (in actions) at the robot's pose, or at ``x, y, yaw``.

    ``x`` and ``y`` must lie on the map's floor (``bounds``), ``|yaw| <= 2 pi``.
    """
    given = {"x": x, "y": y, "yaw": yaw}
    if all(v is None for v in given.values()):
        answer = session.oracle_query()
    else:
        missing = [name for name, v in given.items() if v is None]
        if missing:
            raise BadQueryError(
                "give all of x, y and yaw, or none for the robot's pose", field=missing[0]
            )
        b = session.nav_map.bounds
        for name, value, low, high in (("x", x, b.x_min, b.x_max), ("y", y, b.y_min, b.y_max)):
            if not low <= value <= high:  # type: ignore[operator]
                raise BadQueryError(
                    f"{name}={value:g} is off the map {session.map_name!r}: "
                    f"the floor spans {low:g}..{high:g} m",
                    field=name,
                )
        answer = session.oracle_query((x, y, yaw))  # type: ignore[arg-type]
    return OraclePublic(
        pose=answer.pose,
        optimal_actions=answer.optimal_actions,
        cost_to_go=answer.cost_to_go,
        reachable=answer.cost_to_go is not None,
    )
