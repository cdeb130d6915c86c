"""SPL against hand-computed cases; the random-policy success measurement."""

from __future__ import annotations

import pytest

from services.sim.maps import MAPS_DIR
from services.sim.metrics import random_policy_success_rate, spl, wall_averse_policy_success_rate


def test_spl_hand_computed() -> None:
    assert spl([True], [18], [18]) == 1.0
    assert spl([True], [18], [36]) == 0.5
    assert spl([False], [18], [18]) == 0.0
    # Shorter than the "shortest" path (cannot beat l): capped at 1.
    assert spl([True], [18], [10]) == 1.0
    # (1 * 17/17 + 1 * 18/24 + 0 + 1 * 19/38) / 4 = (1 + 0.75 + 0 + 0.5) / 4
    assert spl([True, True, False, True], [17, 18, 19, 19], [17, 24, 120, 38]) == pytest.approx(
        0.5625
    )


def test_spl_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="equal length"):
        spl([True, False], [18], [18, 20])
    with pytest.raises(ValueError, match="at least one episode"):
        spl([], [], [])
    with pytest.raises(ValueError, match="at least one action"):
        spl([True], [0], [3])
    with pytest.raises(ValueError, match="negative"):
        spl([True], [5], [-1])


def test_random_policy_success_rate_counts() -> None:
    result = random_policy_success_rate(
        "vssg", episodes=30, seed=3, map_path=MAPS_DIR / "open.json"
    )
    assert result.episodes == 30
    assert 0 <= result.successes + result.collisions <= 30
    assert result.success_rate == result.successes / 30
    assert result.collision_rate == result.collisions / 30 > 0.3  # random walks mostly crash
    again = random_policy_success_rate("vssg", episodes=30, seed=3, map_path=MAPS_DIR / "open.json")
    assert again == result
    with pytest.raises(ValueError, match="episodes"):
        random_policy_success_rate(episodes=0)


def test_wall_averse_policy_success_rate_rarely_crashes() -> None:
    kwargs = {"episodes": 20, "seed": 3, "map_path": MAPS_DIR / "open.json"}
    result = wall_averse_policy_success_rate("sssg", **kwargs)
    assert result.episodes == 20
    assert result.success_rate == result.successes / 20
    # Turning away from anything closer than 1 m: almost no collisions (uniform: > 30 %).
    assert result.collision_rate <= 0.1
    assert wall_averse_policy_success_rate("sssg", **kwargs) == result
    # Never forward: it turns in place until the time limit.
    still = wall_averse_policy_success_rate("sssg", forward_probability=0.0, **kwargs)
    assert still.successes == still.collisions == 0
    with pytest.raises(ValueError, match="forward_probability"):
        wall_averse_policy_success_rate(forward_probability=1.5)
    with pytest.raises(ValueError, match="central_rays"):
        wall_averse_policy_success_rate(central_rays=0)
    with pytest.raises(ValueError, match="episodes"):
        wall_averse_policy_success_rate(episodes=0)
