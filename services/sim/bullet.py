"""pybullet without terminal noise: a quiet one-time import and a Husky built from shapes.

pybullet prints a "pybullet build time" banner from C when its module is first imported,
and its URDF importer prints warnings for every link without inertial data (the Husky has
six). Neither can be turned off through the API, and redirecting the process's stdout and
stderr around every env construction is not thread-safe (two threads interleaving the
save/restore leave fd 1 on /dev/null for good). So:

- :data:`pybullet` is imported **once per process**, here, with fds 1 and 2 pointed at
  /dev/null under :data:`_REDIRECT_LOCK` and C's stdio buffers flushed before they are
  restored (the banner is buffered when stdout is a pipe);
- the Husky is built from its meshes with ``createVisualShape`` instead of ``loadURDF``
  (pixel-identical frames, checked in ``tests/sim/test_bullet.py``), so building an env
  prints nothing and needs no redirect.

Every module of the sim imports pybullet from here (``from services.sim.bullet import
pybullet``).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import threading
from pathlib import Path
from types import ModuleType

import pybullet_data

_REDIRECT_LOCK = threading.Lock()
"""Serialises the only fd redirect of the package (the one-time import below)."""


def _import_quietly() -> ModuleType:
    """Import pybullet with its C-level banner sent to /dev/null (once per process)."""
    if "pybullet" in sys.modules:  # imported elsewhere first: the banner is already out
        import pybullet as module

        return module
    with _REDIRECT_LOCK:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
        saved = [os.dup(1), os.dup(2)]
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            import pybullet as module

            ctypes.CDLL(None).fflush(None)  # the banner sits in C's buffer when piped
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in (*saved, devnull):
                os.close(fd)
    return module


pybullet = _import_quietly()

HUSKY_MESH_DIR = Path(pybullet_data.getDataPath()) / "husky" / "meshes"
_BASE_Z = 0.14493
"""Height of the Husky's chassis frame above its footprint (husky.urdf, chassis_joint)."""
_DARK_GREY = (0.3, 0.3, 0.3, 1.0)
HUSKY_VISUALS: tuple[tuple[str, tuple[float, float, float], float, tuple[float, ...]], ...] = (
    ("base_link.stl", (0.0, 0.0, _BASE_Z), 0.0, (0.1, 0.1, 0.1, 1.0)),
    *(
        ("wheel.stl", (sx * 0.256, sy * 0.2854, _BASE_Z + 0.03282), 0.0, _DARK_GREY)
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1))
    ),
    ("top_plate.stl", (0.0, 0.0, _BASE_Z), 0.0, (0.8, 0.8, 0.0, 1.0)),
    ("user_rail.stl", (0.272, 0.0, _BASE_Z + 0.245), 0.0, _DARK_GREY),
    ("bumper.stl", (0.48, 0.0, _BASE_Z + 0.091), 0.0, _DARK_GREY),
    ("bumper.stl", (-0.48, 0.0, _BASE_Z + 0.091), 3.14159, _DARK_GREY),
)
"""pybullet_data's ``husky/husky.urdf`` as visual parts: mesh, position in the footprint
frame (m), yaw (rad), RGBA; the same poses and colours the URDF gives them."""


def connect() -> int:
    """A new pybullet DIRECT client (prints nothing)."""
    return pybullet.connect(pybullet.DIRECT)


def disconnect(client: int) -> None:
    """Release a client; a client already gone is not an error."""
    with contextlib.suppress(pybullet.error):
        pybullet.disconnect(physicsClientId=client)


def add_husky(client: int) -> int:
    """The Husky as a visual-only body (rays and the robot never collide); returns its id.

    Its base frame is the robot's footprint on the floor, as ``base_footprint`` in the URDF.
    """
    shapes = [
        pybullet.createVisualShape(
            pybullet.GEOM_MESH,
            fileName=str(HUSKY_MESH_DIR / mesh),
            visualFramePosition=position,
            visualFrameOrientation=pybullet.getQuaternionFromEuler([0.0, 0.0, yaw]),
            rgbaColor=rgba,
            physicsClientId=client,
        )
        for mesh, position, yaw, rgba in HUSKY_VISUALS
    ]
    n = len(shapes)
    return pybullet.createMultiBody(
        0,
        -1,
        -1,
        basePosition=[0.0, 0.0, 0.0],
        linkMasses=[0.0] * n,
        linkCollisionShapeIndices=[-1] * n,
        linkVisualShapeIndices=shapes,
        linkPositions=[[0.0, 0.0, 0.0]] * n,
        linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
        linkInertialFramePositions=[[0.0, 0.0, 0.0]] * n,
        linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * n,
        linkParentIndices=[0] * n,
        linkJointTypes=[pybullet.JOINT_FIXED] * n,
        linkJointAxis=[[0.0, 0.0, 1.0]] * n,
        physicsClientId=client,
    )
