"""The oracle: optimal actions and cost-to-go at the robot's pose or any pose."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query

from services.sim.deps import SessionDep
from services.sim.schemas import OraclePublic

router = APIRouter(prefix="/sessions/{session_id}/oracle", tags=["oracle"])

FiniteFloat = Annotated[float | None, Query(allow_inf_nan=False)]


@router.get("")
def query_oracle(
    session: SessionDep, x: FiniteFloat = None, y: FiniteFloat = None, yaw: FiniteFloat = None
) -> OraclePublic:
    """Optimal actions and cost-to-go (in actions) at the robot's pose, or at ``x, y, yaw``."""
    if x is not None and y is not None and yaw is not None:
        answer = session.oracle_query((x, y, yaw))
    elif x is None and y is None and yaw is None:
        answer = session.oracle_query()
    else:
        raise HTTPException(422, "give all of x, y and yaw, or none for the robot's pose")
    return OraclePublic(
        pose=answer.pose,
        optimal_actions=answer.optimal_actions,
        cost_to_go=answer.cost_to_go,
        reachable=answer.cost_to_go is not None,
    )
