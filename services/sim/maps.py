"""Navigation maps: a validated JSON schema, loading, and the 2-D collision geometry.

A map is a rectangular floor with walls along its border, box obstacles, a start pose
and a goal. The robot's footprint is a disc of radius :data:`FOOTPRINT_RADIUS_M`, so a
pose collides when its distance to the nearest obstacle or wall is below that radius and
turning in place never collides. The schema is documented in ``docs/sim.md``.
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

FOOTPRINT_RADIUS_M = 0.4
"""Radius of the robot's collision disc (the Husky is 0.99 x 0.67 m; turning in place is free)."""

SWEEP_SAMPLE_M = 0.1
"""Largest spacing of the footprint checks along a move (the sagitta error is < 4 mm)."""

MAPS_DIR = Path(__file__).with_name("maps")
DEFAULT_MAP_PATH = MAPS_DIR / "default.json"

PositiveLength = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Coordinate = Annotated[float, Field(allow_inf_nan=False)]


class MapError(ValueError):
    """A map file is malformed or describes an unusable task; the message says why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Bounds(_Strict):
    """The floor rectangle (m); walls stand just outside it."""

    x_min: Coordinate = 0.0
    x_max: Coordinate
    y_min: Coordinate = 0.0
    y_max: Coordinate

    @model_validator(mode="after")
    def _non_empty(self) -> Bounds:
        if self.x_max <= self.x_min or self.y_max <= self.y_min:
            raise ValueError("bounds must have x_max > x_min and y_max > y_min")
        return self


class Box(_Strict):
    """A box obstacle: centre (m), full size along its own x and y (m), yaw (rad), height (m)."""

    center: tuple[Coordinate, Coordinate]
    size: tuple[PositiveLength, PositiveLength]
    yaw: Coordinate = 0.0
    height: PositiveLength = 1.0


class StartPose(_Strict):
    """The start pose: position (m) and yaw (rad, counter-clockwise from +x)."""

    x: Coordinate
    y: Coordinate
    yaw: Coordinate = 0.0


class Goal(_Strict):
    """The goal position (m) and the radius (m) within which it counts as reached."""

    x: Coordinate
    y: Coordinate
    radius: PositiveLength = 0.5


class MapGeometry:
    """Fast 2-D collision geometry of a map (plain Python, built once per map).

    Distances are to the nearest wall or box surface, negative inside a box; the floor
    bounds act as walls. The robot's footprint is a disc of radius
    :data:`FOOTPRINT_RADIUS_M`.
    """

    __slots__ = ("_boxes", "x_max", "x_min", "y_max", "y_min")

    def __init__(self, bounds: Bounds, boxes: list[Box]) -> None:
        self.x_min, self.x_max = bounds.x_min, bounds.x_max
        self.y_min, self.y_max = bounds.y_min, bounds.y_max
        # (cx, cy, cos yaw, sin yaw, half x, half y) per box.
        self._boxes = tuple(
            (
                b.center[0],
                b.center[1],
                math.cos(b.yaw),
                math.sin(b.yaw),
                b.size[0] / 2.0,
                b.size[1] / 2.0,
            )
            for b in boxes
        )

    def clearance(self, x: float, y: float) -> float:
        """Distance (m) from the point to the nearest wall or box surface (< 0 inside)."""
        nearest = min(x - self.x_min, self.x_max - x, y - self.y_min, self.y_max - y)
        for cx, cy, c, s, hx, hy in self._boxes:
            dx = x - cx
            dy = y - cy
            qx = abs(c * dx + s * dy) - hx
            qy = abs(c * dy - s * dx) - hy
            if qx > 0.0:
                dist = math.hypot(qx, qy) if qy > 0.0 else qx
            else:
                dist = qy if qy > 0.0 else max(qx, qy)
            if dist < nearest:
                nearest = dist
        return nearest

    def clearance_grid(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`clearance` on broadcastable coordinate arrays (float64)."""
        xs = np.asarray(xs, dtype=np.float64)
        ys = np.asarray(ys, dtype=np.float64)
        nearest = np.minimum(
            np.minimum(xs - self.x_min, self.x_max - xs),
            np.minimum(ys - self.y_min, self.y_max - ys),
        )
        for cx, cy, c, s, hx, hy in self._boxes:
            dx = xs - cx
            dy = ys - cy
            qx = np.abs(c * dx + s * dy) - hx
            qy = np.abs(c * dy - s * dx) - hy
            outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
            inside = np.minimum(np.maximum(qx, qy), 0.0)
            nearest = np.minimum(nearest, outside + inside)
        return nearest

    def collides(self, x: float, y: float) -> bool:
        """Whether the footprint disc centred at (x, y) touches a wall or box."""
        return self.clearance(x, y) < FOOTPRINT_RADIUS_M

    def move_collides(self, x0: float, y0: float, x1: float, y1: float) -> bool:
        """Whether the footprint disc touches an obstacle moving from (x0, y0) to (x1, y1).

        The start is assumed free. Clearance is 1-Lipschitz, so when the start's clearance
        exceeds the move length plus the radius the move is free without further checks;
        otherwise the disc is checked at points at most :data:`SWEEP_SAMPLE_M` apart along
        the segment, the end point included.
        """
        length = math.hypot(x1 - x0, y1 - y0)
        if self.clearance(x0, y0) - length >= FOOTPRINT_RADIUS_M:
            return False
        n = max(1, math.ceil(length / SWEEP_SAMPLE_M - 1e-9))
        for k in range(1, n + 1):
            f = k / n
            if self.clearance(x0 + f * (x1 - x0), y0 + f * (y1 - y0)) < FOOTPRINT_RADIUS_M:
                return True
        return False


class NavMap(_Strict):
    """A navigation map: floor bounds, obstacles, start pose, VSSG start jitter and goal.

    :attr:`geometry` answers collision queries (clearance, footprint collisions, swept
    moves).
    """

    name: str = Field(min_length=1)
    description: str = ""
    bounds: Bounds
    wall_thickness: PositiveLength = 0.2
    wall_height: PositiveLength = 1.0
    boxes: list[Box] = Field(default_factory=list)
    start: StartPose
    start_jitter: Annotated[float, Field(ge=0.0, allow_inf_nan=False)] = 0.2
    """Side (m) of the square, centred on the start, from which VSSG starts are drawn."""
    goal: Goal

    _geometry: MapGeometry | None = PrivateAttr(None)

    @property
    def geometry(self) -> MapGeometry:
        """The map's collision geometry (built on first use)."""
        if self._geometry is None:
            self._geometry = MapGeometry(self.bounds, self.boxes)
        return self._geometry

    @model_validator(mode="after")
    def _start_and_goal_usable(self) -> NavMap:
        r = FOOTPRINT_RADIUS_M
        geometry = MapGeometry(self.bounds, self.boxes)
        half_jitter = self.start_jitter / 2.0
        corners = [
            (self.start.x + sx * half_jitter, self.start.y + sy * half_jitter)
            for sx in (-1.0, 0.0, 1.0)
            for sy in (-1.0, 0.0, 1.0)
        ]
        b = self.bounds
        for x, y in corners:
            if not (b.x_min + r <= x <= b.x_max - r and b.y_min + r <= y <= b.y_max - r):
                raise ValueError(
                    f"start area around ({self.start.x}, {self.start.y}) with jitter "
                    f"{self.start_jitter} m leaves the floor (robot radius {r} m)"
                )
        # The whole jitter square must be free: clearance is 1-Lipschitz, so checking the
        # centre against the square's half-diagonal is sufficient.
        start_clearance = geometry.clearance(self.start.x, self.start.y)
        needed = r + half_jitter * math.sqrt(2.0)
        if start_clearance < needed:
            raise ValueError(
                f"start ({self.start.x}, {self.start.y}) is inside or too close to an obstacle "
                f"(clearance {start_clearance:.3f} m, need {needed:.3f} m "
                f"for the robot radius {r} m and start jitter {self.start_jitter} m)"
            )
        if not (b.x_min <= self.goal.x <= b.x_max and b.y_min <= self.goal.y <= b.y_max):
            raise ValueError(f"goal ({self.goal.x}, {self.goal.y}) is outside the floor bounds")
        if math.hypot(self.start.x - self.goal.x, self.start.y - self.goal.y) < self.goal.radius:
            raise ValueError("start lies inside the goal radius")
        return self

    def clearance(self, x: float, y: float) -> float:
        """Shorthand for ``geometry.clearance`` (distance to the nearest obstacle, m)."""
        return self.geometry.clearance(x, y)

    def content_hash(self) -> str:
        """SHA-256 of the canonical JSON of the map (keys caches such as the oracle's)."""
        canonical = json.dumps(self.model_dump(mode="json"), sort_keys=True)
        return hashlib.sha256(canonical.encode()).hexdigest()

    @property
    def diagonal(self) -> float:
        """Length (m) of the floor's diagonal, an upper bound on any in-map distance."""
        b = self.bounds
        return math.hypot(b.x_max - b.x_min, b.y_max - b.y_min)


def wrap_angle(angle: float) -> float:
    """Wrap an angle (rad) to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def parse_map(data: object, *, source: str = "map") -> NavMap:
    """Validate already-parsed JSON data as a :class:`NavMap` (raises :class:`MapError`)."""
    try:
        return NavMap.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}"
            for err in exc.errors()
        )
        raise MapError(f"{source} is not a valid map: {problems}") from None


def load_map(path: str | Path) -> NavMap:
    """Load and validate a JSON map file (schema in ``docs/sim.md``).

    Only the file is checked here; whether the goal can be reached from the start is the
    oracle's job (:meth:`services.sim.oracle.Oracle.check_reachable`, run by the env).

    Raises
    ------
    MapError
        The file is missing, is not JSON, does not follow the schema, or puts the start in
        an obstacle or off the floor.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise MapError(f"cannot read map file {path}: {exc.strerror or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MapError(f"map file {path} is not valid JSON: {exc}") from None
    return parse_map(data, source=f"map file {path}")
