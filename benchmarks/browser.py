"""The browser the dashboard's tests and ``bgrl bench loop`` drive: Debian's Chromium.

Never a downloaded browser; the launch flags keep it off this machine's closed network.
"""

from __future__ import annotations

from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
"""Debian's Chromium (``apt-get install -y chromium``)."""
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
"""Headless launch flags: no sandbox (root), no GPU, no background connections."""
