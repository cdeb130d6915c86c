"""TorchScript export of the greedy pi_HF (loadable with ``torch.jit.load``, no project needed).

The exported module is the observation normalisation plus Fhat. ``forward(obs)`` gives
Fhat's logits (one per action: "this action is judged correct"), ``act(obs)`` the greedy
pi_HF action ``argmax_a sigmoid(Fhat(s, a))``, exactly :meth:`HFPolicy.act
<services.learner.feedback.HFPolicy.act>` without a generator. Observations are the raw
(unnormalised) 13 numbers of the env, one vector or a batch, of any real dtype (numpy's
float64 too); another last dimension is refused with an error saying so.
"""

from __future__ import annotations

import copy
import io
import json
import warnings
from typing import Any

import torch
from torch import nn

from services.learner.feedback import FeedbackModel
from services.learner.networks import exported_observations

META_FILE = "bgrl_meta.json"
"""Extra file inside the TorchScript archive with the session's description and metrics."""


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
    torch.jit.save(scripted, buffer, _extra_files={META_FILE: json.dumps(meta, allow_nan=False)})
    return buffer.getvalue()
