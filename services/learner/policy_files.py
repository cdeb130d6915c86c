"""A trained policy as a ``torch.export`` program (``.pt2``) and as ONNX, beside TorchScript.

Both hold the fixed observation normalisation and the network: raw float32 observations of
shape ``(batch, n_obs)`` (any batch >= 1) go in, one logit per action comes out, and the greedy
action is their argmax. For the guided-PPO policy the logits are pi_RL's
(:class:`ActorLogits`); for pi_HF they are Fhat's
(:class:`~services.learner.service.export.HFPolicyExport`). The ONNX graph's input is named
``obs`` and its output ``logits``. Each file carries the TorchScript file's description
(``bgrl_meta.json``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

from services.core.model_formats import META_KEY, SUFFIXES, ModelFormat
from services.model_export import export_program, save_onnx, save_pt2

PORTABLE_FORMATS: tuple[ModelFormat, ...] = ("pt2", "onnx")
"""The formats written beside a policy's TorchScript file."""


class ActorLogits(nn.Module):
    """pi_RL's action logits for a batch of raw observations: the agent's normalisation and
    actor (the critic's output is dropped)."""

    def __init__(self, agent: nn.Module) -> None:  # an ActorCritic: obs -> (logits, value)
        super().__init__()
        self.agent = agent

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(batch, n_obs) float32 -> (batch, n_actions) logits."""
        logits, _ = self.agent(obs)
        return logits


def write_portable(
    module: nn.Module, n_obs: int, meta: dict[str, Any], stem: Path
) -> dict[ModelFormat, Path]:
    """Write ``module`` (observations -> logits) as ``<stem>.pt2`` and ``<stem>.onnx``."""
    program = export_program(module, torch.zeros((2, n_obs), dtype=torch.float32))
    return {
        "pt2": save_pt2(program, stem.with_suffix(SUFFIXES["pt2"]), meta),
        "onnx": save_onnx(
            program,
            stem.with_suffix(SUFFIXES["onnx"]),
            meta,
            input_name="obs",
            output_name="logits",
        ),
    }


def write_beside_torchscript(agent: nn.Module, torchscript_path: Path) -> dict[ModelFormat, Path]:
    """Write the PPO ``agent`` as ``.pt2`` and ``.onnx`` beside its TorchScript file (same
    name, other ending), with that file's description inside."""
    extra = {META_KEY: ""}
    torch.jit.load(str(torchscript_path), map_location="cpu", _extra_files=extra)
    meta = json.loads(extra[META_KEY]) if extra[META_KEY] else {}
    n_obs = int(agent.normalizer.n_obs)
    return write_portable(ActorLogits(agent).eval(), n_obs, meta, torchscript_path)
