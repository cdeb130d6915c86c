"""The discrete action set of the navigation task and the ErrP trigger codes.

Shared by the simulator (which executes actions and emits markers), the EEG service
(which reads the markers from recordings and streams) and the learner.
"""

from __future__ import annotations

from enum import IntEnum


class Action(IntEnum):
    """The robot's three actions (paper §Experiments)."""

    FORWARD = 0
    """Move forward 0.3 m."""
    TURN_LEFT = 1
    """Turn 30 degrees counter-clockwise."""
    TURN_RIGHT = 2
    """Turn 30 degrees clockwise."""


N_ACTIONS = len(Action)
FORWARD_STEP_M = 0.3
TURN_STEP_RAD = 0.5235987755982988  # 30 degrees

TRIGGER_CORRECT = 1
"""Status/trigger code of an action the oracle judges optimal."""
TRIGGER_ERROR = 2
"""Status/trigger code of an action the oracle judges sub-optimal (an error)."""

ACTION_PERIOD_S = 1.5
"""One action every 1.5 s while a human observes (paper §Experiments)."""
