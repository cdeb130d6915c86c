"""Request (``*Create`` / ``*Request``) and response (``*Public``) schemas of the sim service."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from services.core.actions import Action
from services.core.markers import ActionMarker
from services.core.schemas import ActionValue, FiniteModel, Seed, StrictRequest
from services.sim.sessions import FrameView, PacedPolicy

Observation = list[float | None]


class SessionCreate(StrictRequest):
    """Open a sim session: one env, reset once with ``seed``."""

    task: Literal["sssg", "vssg"] = Field(
        "sssg", description="sssg: single start single goal; vssg: start jittered 0.2 x 0.2 m."
    )
    map: str | None = Field(
        None,
        max_length=1024,
        description="Name (e.g. 'default') or path of a map the service ships or is "
        "configured with; default map when omitted. GET /maps lists them.",
    )
    seed: Seed | None = Field(None, description="Seed of the first reset (random if None).")
    reward_mode: Literal["sparse", "rich", "dense"] = "sparse"


class PacedPublic(BaseModel):
    """State of a session's paced mode."""

    model_config = ConfigDict(from_attributes=True)

    running: bool
    policy: PacedPolicy | None
    period_s: float | None
    auto_reset: bool
    max_actions: int | None
    actions_executed: int
    queued_actions: int
    error: str | None = Field(description="Why the paced mode stopped on an error, if it did.")


class SessionPublic(BaseModel):
    """A sim session and its current state."""

    model_config = ConfigDict(from_attributes=True)

    id: str
    task: str
    reward_mode: str
    map: str
    seed: int | None
    created_at: float = Field(description="Unix time (s) the session was opened.")
    episode: int = Field(description="Current episode index (0-based).")
    step: int = Field(description="Actions executed in this session so far.")
    episode_step: int = Field(description="Actions executed in the current episode so far.")
    pose: tuple[float, float, float] = Field(description="(x m, y m, yaw rad) of the robot.")
    observation: Observation = Field(description="The env's 13-float observation.")
    reward: float | None = Field(description="Reward of the last step (None right after reset).")
    terminated: bool
    truncated: bool
    info: dict[str, Any]
    last_marker: ActionMarker | None
    paced: PacedPublic


class ResetRequest(StrictRequest):
    """Start a new episode."""

    seed: Seed | None = Field(None, description="Reseed the env (None: continue its RNG).")


class ResetPublic(BaseModel):
    """The first observation of a new episode."""

    episode: int
    observation: Observation
    info: dict[str, Any] = Field(description="Includes shortest_path_steps and pose.")


class StepRequest(StrictRequest):
    """Execute one action."""

    action: ActionValue


class StepPublic(BaseModel):
    """What the action produced, when it happened and how the oracle judged it."""

    observation: Observation
    reward: float
    terminated: bool
    truncated: bool
    info: dict[str, Any] = Field(description="Includes is_success, collision and pose.")
    timestamp: float = Field(description="LSL clock time (s) the action was executed.")
    marker: ActionMarker = Field(description="The marker published for this action.")


class OraclePublic(BaseModel):
    """The oracle's answer for one pose."""

    pose: tuple[float, float, float]
    optimal_actions: list[Action]
    cost_to_go: float | None = Field(description="Actions to the goal; None if unreachable.")
    reachable: bool


class PacedCreate(StrictRequest):
    """Start the paced mode: one action every ``period_s`` for human observers."""

    policy: PacedPolicy = PacedPolicy.RANDOM
    period_s: float | None = Field(
        None, ge=0.05, le=60.0, description="Seconds per action (service default: 1.5)."
    )
    auto_reset: bool = Field(
        True, description="Reset one period after an episode ends (else stop there)."
    )
    max_actions: int | None = Field(
        None, strict=True, ge=1, le=10**9, description="Stop after this many actions."
    )


class QueueRequest(StrictRequest):
    """Actions for the paced ``queue`` policy, executed in order, one per period."""

    actions: list[ActionValue] = Field(min_length=1, max_length=1000)


class QueuePublic(BaseModel):
    """Length of the paced-mode action queue."""

    queued_actions: int


class MapPublic(BaseModel):
    """A map sessions can use."""

    name: str = Field(description="Pass it as ``map`` to POST /sessions.")
    default: bool = Field(description="Used when a session names no map.")
    description: str = Field(description="What the map is for (from its file).")


FrameFormat = Literal["jpeg", "png"]
FrameEncoding = Literal["base64", "binary"]
MAX_FPS = 30.0
"""Upper bound of the frame rate, also when frames follow actions."""


class StreamParams(FiniteModel):
    """Query parameters of ``WS /sessions/{id}/stream`` (validated after the handshake, so a
    bad one gets close code 4422 naming it rather than a bare handshake refusal)."""

    model_config = ConfigDict(extra="ignore", populate_by_name=True)

    fps: float | None = Field(None, ge=1.0, le=MAX_FPS, description="Periodic frames per second.")
    on_action: bool = Field(True, description="Also send a frame right after each step/reset.")
    view: FrameView = "camera"
    image_format: FrameFormat = Field("jpeg", alias="format")
    encoding: FrameEncoding = "base64"
