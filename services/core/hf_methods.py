"""Names of the learner's stage-2 methods (docs/stage2.md) for the layers that cannot import
the learner (core, api, client): the learner's ``HF_METHODS``, kept equal by a test."""

from __future__ import annotations

from typing import Literal

HFMethodName = Literal[
    "paper",
    "noise_aware",
    "categorical",
    "thompson",
    "categorical_thompson",
    "categorical_info",
    "categorical_onpolicy",
    "categorical_kernel",
]
"""Stage-2 methods that learn pi_HF; the learner's ``HF_METHODS``."""
HF_METHOD_NAMES: tuple[str, ...] = HFMethodName.__args__  # type: ignore[attr-defined]
