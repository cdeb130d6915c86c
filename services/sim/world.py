"""The pybullet world of a map (walls, boxes, floor, goal pillar) and the worlds headless
envs share.

Rays hit only the walls and boxes, which never move, and a headless env (no
``render_mode``: every training, sweep and stage-2 env) puts nothing else in its world, so
the headless envs of one map in a process cast their rays in one shared world: one
``pybullet.connect(DIRECT)`` (~27 MB of a ~28 MB env) and one copy of the walls for all of
them, built the same way as a private world (the same bodies in the same order, so the same
rays; ``tests/sim/test_bullet.py``). An env that renders keeps a private world, with the
Husky it moves for its frames. pybullet never releases the GIL, so threads sharing a world
take turns call by call.

A map's rays from a pose depend on the pose only (the walls and boxes never move), so the
rays cast from each (x, y, heading) are remembered per world (:class:`RayMemo`): a robot
turning on the spot, the repeated first steps of SSSG's fixed start and a policy's paths
in later episodes cast each ray set once (about half of a sweep's casts).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from services.sim import bullet, rendering
from services.sim.bullet import pybullet
from services.sim.maps import NavMap

RAY_MEMO_MAX_POSES = 50_000
"""Poses whose rays a :class:`RayMemo` keeps (~26 MB); a full memo is emptied."""

RAY_HEIGHT_M = 0.4
"""Rays are cast this high above the floor (lower under a lower wall or box)."""


def build_world(client: int, nav_map: NavMap, *, husky: bool) -> tuple[int | None, float]:
    """Create floor, walls, boxes, goal pillar and (``husky``) the Husky in ``client``;
    returns the Husky's body id (None without it) and the rays' height.

    Rays are cast below the lowest obstacle's half height, so the floor needs no collision
    shape.
    """
    m = nav_map
    # visual only (rays never hit the robot), and ~9 MB of meshes: built for frames only
    robot = bullet.add_husky(client) if husky else None

    def add_box(cx: float, cy: float, sx: float, sy: float, h: float, yaw: float, rgba):
        half = [sx / 2.0, sy / 2.0, h / 2.0]
        col = pybullet.createCollisionShape(
            pybullet.GEOM_BOX, halfExtents=half, physicsClientId=client
        )
        vis = pybullet.createVisualShape(
            pybullet.GEOM_BOX, halfExtents=half, rgbaColor=rgba, physicsClientId=client
        )
        pybullet.createMultiBody(
            0,
            col,
            vis,
            basePosition=[cx, cy, h / 2.0],
            baseOrientation=pybullet.getQuaternionFromEuler([0.0, 0.0, yaw]),
            physicsClientId=client,
        )

    b, t, wh = m.bounds, m.wall_thickness, m.wall_height
    width, depth = b.x_max - b.x_min, b.y_max - b.y_min
    mid_x, mid_y = (b.x_min + b.x_max) / 2.0, (b.y_min + b.y_max) / 2.0
    wall_rgba = rendering.WALL_RGBA
    add_box(mid_x, b.y_min - t / 2, width + 2 * t, t, wh, 0.0, wall_rgba)
    add_box(mid_x, b.y_max + t / 2, width + 2 * t, t, wh, 0.0, wall_rgba)
    add_box(b.x_min - t / 2, mid_y, t, depth, wh, 0.0, wall_rgba)
    add_box(b.x_max + t / 2, mid_y, t, depth, wh, 0.0, wall_rgba)
    for box in m.boxes:
        add_box(*box.center, *box.size, box.height, box.yaw, rendering.OBSTACLE_RGBA)
    # The floor is a flat visual box (TinyRenderer draws it far faster than
    # plane.urdf's large textured mesh).
    floor = pybullet.createVisualShape(
        pybullet.GEOM_BOX,
        halfExtents=[width / 2 + t, depth / 2 + t, 0.005],
        rgbaColor=rendering.FLOOR_RGBA,
        physicsClientId=client,
    )
    pybullet.createMultiBody(
        0, -1, floor, basePosition=[mid_x, mid_y, -0.005], physicsClientId=client
    )
    # The goal pillar is visual only: it neither blocks the robot nor the rays.
    pillar = pybullet.createVisualShape(
        pybullet.GEOM_BOX,
        halfExtents=[0.15, 0.15, 0.75],
        rgbaColor=rendering.GOAL_RGBA,
        physicsClientId=client,
    )
    pybullet.createMultiBody(
        0, -1, pillar, basePosition=[m.goal.x, m.goal.y, 0.75], physicsClientId=client
    )
    ray_z = min(RAY_HEIGHT_M, 0.5 * min([wh, *(box.height for box in m.boxes)]))
    return robot, ray_z


class RayMemo(dict[tuple[float, float, int], tuple[float, ...]]):
    """The ray distances cast in one world from each pose (x, y, heading index), at most
    :data:`RAY_MEMO_MAX_POSES` of them (emptied when full)."""

    def remember(self, pose: tuple[float, float, int], rays: tuple[float, ...]) -> None:
        """Keep ``rays`` as cast from ``pose``."""
        if len(self) >= RAY_MEMO_MAX_POSES:
            self.clear()
        self[pose] = rays


@dataclass
class _SharedWorld:
    client: int
    ray_z: float
    users: int
    rays: RayMemo


_shared_lock = threading.Lock()
_shared: dict[str, _SharedWorld] = {}


def acquire_shared_world(nav_map: NavMap) -> tuple[int, float, RayMemo]:
    """The client, ray height and ray memo of the map's shared headless world (built on
    first use); every call needs its :func:`release_shared_world`."""
    key = nav_map.content_hash()
    with _shared_lock:
        world = _shared.get(key)
        if world is None:
            client = bullet.connect()
            try:
                _, ray_z = build_world(client, nav_map, husky=False)
            except BaseException:
                bullet.disconnect(client)
                raise
            world = _shared[key] = _SharedWorld(client, ray_z, 0, RayMemo())
        world.users += 1
        return world.client, world.ray_z, world.rays


def release_shared_world(nav_map: NavMap) -> None:
    """One user of the map's shared world is done; the last one disconnects it."""
    key = nav_map.content_hash()
    with _shared_lock:
        world = _shared[key]
        world.users -= 1
        if world.users == 0:
            del _shared[key]
            bullet.disconnect(world.client)
