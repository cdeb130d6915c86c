"""The learning-curve plot of a job (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def curve_png(curve: Sequence[Sequence[float]], title: str) -> bytes:
    """PNG of success weighted by path length (SPL) against environment steps."""
    steps = [point[0] for point in curve]
    spl = [point[1] for point in curve]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    try:
        ax.plot(steps, spl, marker="o", markersize=3)
        ax.set_xlabel("environment steps")
        ax.set_ylabel("SPL (greedy policy)")
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(title)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png")
        return buffer.getvalue()
    finally:
        plt.close(fig)
