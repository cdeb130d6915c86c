"""The learning-curve plot of a job (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt


def curve_png(
    curve: Sequence[Sequence[float]], title: str, *, hf_policy_spl: float | None = None
) -> bytes:
    """PNG of success weighted by path length (SPL) against environment steps; with
    ``hf_policy_spl``, the human-feedback policy's SPL as a dashed line (as the dashboard
    draws it)."""
    steps = [point[0] for point in curve]
    spl = [point[1] for point in curve]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    try:
        ax.plot(steps, spl, marker="o", markersize=3, label="π_RL (greedy)")
        if hf_policy_spl is not None:
            ax.axhline(hf_policy_spl, linestyle="--", color="tab:orange", label="π_HF")
            ax.legend(loc="lower right")
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
