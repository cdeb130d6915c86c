"""Names of the stage-2 methods (docs/stage2.md), here in core so that every layer can name
them (the api and core cannot import the learner); a test keeps them equal to the learner's
``HF_METHODS``."""

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
    "bayes_query",
    "bayes_query_flat",
]
"""Stage-2 methods that learn pi_HF; the learner's ``HF_METHODS``."""
HF_METHOD_NAMES: tuple[str, ...] = HFMethodName.__args__  # type: ignore[attr-defined]
