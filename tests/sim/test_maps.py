"""Map loading and validation: every bad map is rejected with a message naming the problem."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.sim.env import BrainNavEnv
from services.sim.maps import (
    DEFAULT_MAP_PATH,
    MAPS_DIR,
    MapError,
    NavMap,
    load_map,
    parse_map,
)


def base_map() -> dict:
    return {
        "name": "room",
        "bounds": {"x_max": 4.0, "y_max": 3.0},
        "boxes": [{"center": [2.0, 1.5], "size": [0.4, 0.4]}],
        "start": {"x": 1.0, "y": 1.5, "yaw": 0.0},
        "goal": {"x": 3.2, "y": 1.5},
    }


def write(tmp_path: Path, data: object) -> Path:
    path = tmp_path / "map.json"
    path.write_text(json.dumps(data) if not isinstance(data, str) else data)
    return path


def test_shipped_maps_load() -> None:
    default = load_map(DEFAULT_MAP_PATH)
    assert isinstance(default, NavMap) and default.name == "default"
    b = default.bounds
    assert (b.x_max - b.x_min, b.y_max - b.y_min) == (11.0, 12.0)
    assert default.goal.radius == 0.5 and default.start_jitter == 0.2
    for path in MAPS_DIR.glob("*.json"):
        load_map(path)


def test_valid_custom_map(tmp_path: Path) -> None:
    geometry = load_map(write(tmp_path, base_map())).geometry
    assert geometry.clearance(1.0, 1.5) == pytest.approx(0.8)  # box face at x = 1.8
    assert geometry.clearance(2.0, 1.5) == pytest.approx(-0.2)  # box centre
    assert geometry.clearance(1.5, 0.2) == pytest.approx(0.2)  # floor edge y = 0
    assert geometry.clearance(2.5, 2.0) == pytest.approx(math.hypot(0.3, 0.3))  # box corner
    assert geometry.collides(1.5, 1.5) and not geometry.collides(1.0, 1.5)
    assert geometry.move_collides(1.0, 1.5, 1.5, 1.5)
    assert not geometry.move_collides(1.0, 1.5, 1.0, 1.8)
    # The vectorised grid agrees with the scalar clearance.
    grid = geometry.clearance_grid(np.array([1.0, 2.0]), np.array([1.5, 1.5]))
    np.testing.assert_allclose(grid, [0.8, -0.2])


def test_rotated_box_clearance() -> None:
    data = base_map()
    data["boxes"] = [{"center": [2.0, 1.5], "size": [1.0, 0.2], "yaw": math.pi / 2}]
    geometry = parse_map(data).geometry
    assert geometry.clearance(2.0, 2.1) == pytest.approx(0.1)  # rotated: 1 m along y
    assert geometry.clearance(1.5, 1.5) == pytest.approx(0.4)


def test_content_hash_tracks_content() -> None:
    a = parse_map(base_map())
    data = base_map()
    data["goal"]["x"] = 3.3
    assert a.content_hash() == parse_map(base_map()).content_hash()
    assert a.content_hash() != parse_map(data).content_hash()


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("goal"), "goal"),
        (lambda d: d["boxes"][0].update(size=[-1.0, 0.4]), "size"),
        (lambda d: d["bounds"].update(x_max=-1.0), "x_max > x_min"),
        (lambda d: d.update(colour="red"), "colour"),
        (lambda d: d["start"].update(x=1.9), "inside or too close to an obstacle"),
        (lambda d: d["start"].update(x=0.2), "leaves the floor"),
        (lambda d: d["goal"].update(x=9.0), "outside the floor"),
        (lambda d: d["goal"].update(x=1.2), "inside the goal radius"),
        (lambda d: d["start"].update(yaw=float("nan")), "yaw"),
    ],
)
def test_invalid_maps_are_rejected(tmp_path: Path, mutate, message: str) -> None:
    data = base_map()
    mutate(data)
    with pytest.raises(MapError, match=message):
        load_map(write(tmp_path, data))


def test_unreachable_goal_is_rejected_by_the_oracle_not_the_loader(tmp_path: Path) -> None:
    data = base_map()
    data["boxes"] = [{"center": [2.0, 1.5], "size": [0.4, 3.0]}]  # wall across the room
    path = write(tmp_path, data)
    load_map(path)  # the schema itself is fine; only reachability fails
    with pytest.raises(MapError, match="cannot be reached"):
        BrainNavEnv(map_path=path)


def test_map_module_does_not_import_the_oracle() -> None:
    code = "import sys, services.sim.maps; print('services.sim.oracle' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout == "False\n"


def test_malformed_and_missing_files(tmp_path: Path) -> None:
    with pytest.raises(MapError, match="not valid JSON"):
        load_map(write(tmp_path, "{not json"))
    with pytest.raises(MapError, match="cannot read map file"):
        load_map(tmp_path / "absent.json")
    with pytest.raises(MapError, match="not a valid map"):
        load_map(write(tmp_path, [1, 2, 3]))
