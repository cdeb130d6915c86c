"""The greedy pi_HF as files: TorchScript (``torch.jit.load``, no project needed), a
``torch.export`` program (``.pt2``) and ONNX (:mod:`~services.learner.policy_files`).

The exported module is the observation normalisation plus Fhat. ``forward(obs)`` gives
Fhat's logits (one per action: "this action is judged correct"), ``act(obs)`` the greedy
pi_HF action ``argmax_a sigmoid(Fhat(s, a))``, exactly :meth:`HFPolicy.act
<services.learner.feedback.HFPolicy.act>` without a generator. Observations are the raw
(unnormalised) 13 numbers of the env, one vector or a batch, of any real dtype (numpy's
float64 too); another last dimension is refused with an error saying so. The ``.pt2`` and
ONNX files take float32 batches ``(batch, n_obs)`` and give ``forward``'s logits.
"""

from __future__ import annotations

import copy
import io
import json
import tempfile
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn

from services.core.model_formats import META_KEY, ModelFormat
from services.learner.feedback import FeedbackModel
from services.learner.networks import exported_observations
from services.learner.policy_files import write_portable


class HFPolicyExport(nn.Module):
    """Normalisation + Fhat; ``act`` is the greedy pi_HF."""

    def __init__(self, model: FeedbackModel) -> None:
        super().__init__()
        self.model = model
        self.n_obs: int = model.normalizer.n_obs

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Fhat's logits for raw observations (..., n_obs) of any real dtype, shape (..., 3)."""
        return self.model(exported_observations(obs, self.n_obs))

    @torch.jit.export
    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """Greedy action(s) of pi_HF."""
        return torch.argmax(torch.sigmoid(self.forward(obs)), dim=-1)


def torchscript_bytes(model: FeedbackModel, meta: dict[str, Any]) -> bytes:
    """The scripted :class:`HFPolicyExport` of a copy of ``model``, ``meta`` inside as JSON."""
    module = HFPolicyExport(copy.deepcopy(model)).eval()
    with warnings.catch_warnings():  # TorchScript is deprecated but still the portable format
        warnings.simplefilter("ignore", DeprecationWarning)
        scripted = torch.jit.script(module)
    buffer = io.BytesIO()
    torch.jit.save(scripted, buffer, _extra_files={META_KEY: json.dumps(meta, allow_nan=False)})
    return buffer.getvalue()


def policy_files(model: FeedbackModel, meta: dict[str, Any]) -> dict[ModelFormat, bytes]:
    """pi_HF of a copy of ``model`` in every format (TorchScript, ``.pt2``, ONNX), ``meta``
    inside each."""
    files: dict[ModelFormat, bytes] = {"torchscript": torchscript_bytes(model, meta)}
    module = HFPolicyExport(copy.deepcopy(model)).eval()
    with tempfile.TemporaryDirectory(prefix="bgrl-hf-policy-") as tmp:
        written = write_portable(module, module.n_obs, meta, Path(tmp) / "hf_policy")
        files.update({fmt: path.read_bytes() for fmt, path in written.items()})
    return files
