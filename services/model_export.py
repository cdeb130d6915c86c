"""Write a torch module as a ``torch.export`` program (``.pt2``) and as ONNX.

Shared by the learner (guided-PPO policy, pi_HF) and the EEG decoders; the format names are in
:mod:`services.core.model_formats`. Both take one float32 input whose first dimension is the
batch (any size >= 1) and embed a JSON description under :data:`META_KEY`. The ONNX file is
converted from the same exported program, so the two graphs are one.
"""

from __future__ import annotations

import json
import logging
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn
from torch.export import ExportedProgram

from services.core.files import finite_or_null
from services.core.model_formats import META_KEY

# Library notices that say nothing about our models, filtered where they arise (only these
# messages): torch 2.13 deprecates TorchScript, which is still offered; the ONNX exporter warns
# about a pytree API it uses itself, and logs that torchvision (not used here) is missing.
warnings.filterwarnings(
    "ignore", message=r"`torch\.jit\.script` is deprecated", category=DeprecationWarning
)
warnings.filterwarnings(
    "ignore", message=r"`isinstance\(treespec, LeafSpec\)` is deprecated", category=FutureWarning
)


def _not_torchvision_notice(record: logging.LogRecord) -> bool:
    return "torchvision is not installed" not in record.getMessage()


logging.getLogger("torch.onnx._internal.exporter._registration").addFilter(_not_torchvision_notice)


def meta_json(meta: dict[str, Any]) -> str:
    """``meta`` as strict JSON (a figure without a value, NaN, as ``null``)."""
    return json.dumps(finite_or_null(meta), allow_nan=False)


def export_program(module: nn.Module, example: torch.Tensor) -> ExportedProgram:
    """``module`` (in eval mode) traced by ``torch.export`` for a batch of any size >= 1.

    ``example`` is one input batch (its first dimension becomes dynamic; use 2 or more rows:
    a batch of 1 would be specialised).
    """
    batch = torch.export.Dim("batch", min=1)
    return torch.export.export(module.eval(), (example,), dynamic_shapes=({0: batch},))


def save_pt2(program: ExportedProgram, path: str | Path, meta: dict[str, Any]) -> Path:
    """Write ``program`` to ``path`` with ``meta`` inside as JSON (``torch.export.load``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra = {META_KEY: meta_json(meta)}
    torch.export.save(program, str(path), extra_files=extra)
    return path


def save_onnx(
    program: ExportedProgram,
    path: str | Path,
    meta: dict[str, Any],
    *,
    input_name: str,
    output_name: str,
) -> Path:
    """Convert ``program`` to ONNX (input ``input_name``, output ``output_name``, dynamic
    batch) and write it to ``path`` with ``meta`` as the metadata property :data:`META_KEY`.

    Uses torch's dynamo exporter (``onnx`` and ``onnxscript``; offline; about a second).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx_program = torch.onnx.export(
        program, input_names=[input_name], output_names=[output_name], dynamo=True, verbose=False
    )
    onnx_program.model.metadata_props[META_KEY] = meta_json(meta)
    onnx_program.save(str(path))
    return path


def read_pt2_meta(path: str | Path) -> dict[str, Any]:
    """The JSON description inside a ``.pt2`` file written by :func:`save_pt2`."""
    extra = {META_KEY: ""}
    torch.export.load(str(path), extra_files=extra)
    return json.loads(extra[META_KEY])
