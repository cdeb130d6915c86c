"""Images of the navigation env: a third-person TinyRenderer frame and a fast top-down map."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from services.sim.bullet import pybullet
from services.sim.maps import FOOTPRINT_RADIUS_M, NavMap

FRAME_WIDTH = 320
FRAME_HEIGHT = 240
TOP_DOWN_PX_PER_M = 40.0

FLOOR_RGBA = (0.86, 0.86, 0.82, 1.0)
WALL_RGBA = (0.75, 0.72, 0.68, 1.0)
OBSTACLE_RGBA = (0.55, 0.42, 0.30, 1.0)
GOAL_RGBA = (0.10, 0.30, 0.95, 1.0)

_FLOOR_RGB = (236, 236, 230)
_WALL_RGB = (120, 116, 110)
_OBSTACLE_RGB = (140, 107, 76)
_GOAL_RGB = (26, 77, 242)
_ROBOT_RGB = (235, 180, 20)
_PATH_RGB = (220, 40, 40)
_RAY_RGB = (230, 30, 30)

_backgrounds: dict[str, np.ndarray] = {}


def third_person_frame(
    client: int,
    pose: tuple[float, float, float],
    rays: Sequence[float],
    ray_z: float,
    ray_angles: np.ndarray,
    width: int = FRAME_WIDTH,
    height: int = FRAME_HEIGHT,
) -> np.ndarray:
    """Render a chase-camera frame with TinyRenderer and draw the range rays on it.

    Returns an (height, width, 3) uint8 RGB array.
    """
    x, y, yaw = pose
    cos_y, sin_y = math.cos(yaw), math.sin(yaw)
    eye = [x - 3.0 * cos_y, y - 3.0 * sin_y, 2.6]
    target = [x + 1.5 * cos_y, y + 1.5 * sin_y, 0.2]
    view = pybullet.computeViewMatrix(eye, target, [0.0, 0.0, 1.0], physicsClientId=client)
    proj = pybullet.computeProjectionMatrixFOV(
        fov=60.0, aspect=width / height, nearVal=0.1, farVal=40.0, physicsClientId=client
    )
    _, _, rgba, _, _ = pybullet.getCameraImage(
        width,
        height,
        view,
        proj,
        renderer=pybullet.ER_TINY_RENDERER,
        physicsClientId=client,
    )
    frame = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3]
    # Project the rays with the same matrices (column-major 4x4) and draw them.
    clip_from_world = (
        np.asarray(proj, dtype=np.float64).reshape(4, 4).T
        @ np.asarray(view, dtype=np.float64).reshape(4, 4).T
    )
    angles = yaw + np.asarray(ray_angles, dtype=np.float64)
    dist = np.asarray(rays, dtype=np.float64)
    ends = np.stack(
        [x + dist * np.cos(angles), y + dist * np.sin(angles), np.full_like(dist, ray_z)], axis=1
    )
    points = np.vstack([[x, y, ray_z], ends])
    clip = np.hstack([points, np.ones((len(points), 1))]) @ clip_from_world.T
    visible = clip[:, 3] > 1e-6
    ndc = clip[:, :2] / np.where(visible, clip[:, 3], 1.0)[:, None]
    px = (ndc[:, 0] + 1.0) * 0.5 * width
    py = (1.0 - ndc[:, 1]) * 0.5 * height
    image = Image.fromarray(np.ascontiguousarray(frame))
    draw = ImageDraw.Draw(image)
    if visible[0]:
        for i in range(1, len(points)):
            if visible[i]:
                draw.line([(px[0], py[0]), (px[i], py[i])], fill=_RAY_RGB, width=1)
    return np.asarray(image, dtype=np.uint8)


def _background(nav_map: NavMap) -> np.ndarray:
    """The static top-down raster (floor, walls, obstacles), cached per map."""
    key = nav_map.content_hash()
    cached = _backgrounds.get(key)
    if cached is not None:
        return cached
    b, t = nav_map.bounds, nav_map.wall_thickness
    s = TOP_DOWN_PX_PER_M
    width = math.ceil((b.x_max - b.x_min + 2 * t) * s)
    height = math.ceil((b.y_max - b.y_min + 2 * t) * s)
    xs = b.x_min - t + (np.arange(width) + 0.5) / s
    ys = b.y_max + t - (np.arange(height) + 0.5) / s
    image = np.empty((height, width, 3), dtype=np.uint8)
    image[:] = _FLOOR_RGB
    outside = (
        (xs[None, :] < b.x_min)
        | (xs[None, :] > b.x_max)
        | (ys[:, None] < b.y_min)
        | (ys[:, None] > b.y_max)
    )
    image[outside] = _WALL_RGB
    in_box = nav_map.geometry.clearance_grid(xs[None, :], ys[:, None]) < 0.0
    image[in_box & ~outside] = _OBSTACLE_RGB
    image.flags.writeable = False
    _backgrounds[key] = image
    return image


def top_down_image(
    nav_map: NavMap,
    pose: tuple[float, float, float] | None,
    trajectory: Sequence[tuple[float, float]] = (),
) -> np.ndarray:
    """A top-down (H, W, 3) uint8 image: map, goal, trajectory and the robot (if ``pose``).

    40 pixels per metre, +x to the right and +y up.
    """
    b, t = nav_map.bounds, nav_map.wall_thickness
    s = TOP_DOWN_PX_PER_M

    def to_px(x: float, y: float) -> tuple[float, float]:
        return ((x - b.x_min + t) * s, (b.y_max + t - y) * s)

    image = Image.fromarray(_background(nav_map).copy())
    draw = ImageDraw.Draw(image)
    gx, gy = to_px(nav_map.goal.x, nav_map.goal.y)
    gr = nav_map.goal.radius * s
    draw.ellipse([gx - gr, gy - gr, gx + gr, gy + gr], outline=_GOAL_RGB, width=2)
    draw.rectangle([gx - 0.15 * s, gy - 0.15 * s, gx + 0.15 * s, gy + 0.15 * s], fill=_GOAL_RGB)
    if len(trajectory) >= 2:
        draw.line([to_px(float(x), float(y)) for x, y in trajectory], fill=_PATH_RGB, width=2)
    if pose is not None:
        x, y, yaw = pose
        cx, cy = to_px(x, y)
        r = FOOTPRINT_RADIUS_M * s
        draw.ellipse([cx - r, cy - r, cx + r, cy + r], fill=_ROBOT_RGB, outline=(60, 60, 60))
        draw.line(
            [(cx, cy), (cx + r * math.cos(yaw), cy - r * math.sin(yaw))], fill=(0, 0, 0), width=3
        )
    return np.asarray(image, dtype=np.uint8)
