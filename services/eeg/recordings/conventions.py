"""The conventions every recording follows, wherever it comes from or goes to.

Files, live streams, the virtual subject and the live recorder all agree on these: actions
are codes in a ``Status`` trigger channel (1 correct, 2 error:
:data:`~services.core.actions.TRIGGER_CORRECT`, :data:`~services.core.actions.TRIGGER_ERROR`),
read from its low byte, written as short pulses; generated data carry a ``SYNTHETIC`` mark.
"""

from __future__ import annotations

STIM_CHANNEL = "Status"
"""Name of the trigger channel holding the action codes."""
TRIGGER_MASK = 0xFF
"""Low byte of ``Status``: BioSemi amplifiers set status flags in the upper bits."""
TRIGGER_PULSE_S = 0.01
"""Width of each trigger pulse written to a ``Status`` channel (s)."""
SYNTHETIC_TAG = "SYNTHETIC"
"""Start of ``raw.info["description"]`` (and of a BDF header's recording field) of generated
data (a virtual subject)."""
SYNTHETIC_ELEMENT = "synthetic"
"""Element of an LSL stream's description (and of an XDF stream's) that marks generated data."""
