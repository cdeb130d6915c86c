"""The file formats a trained model is offered in (names only: no torch here).

``torchscript``
    ``torch.jit.load`` (and libtorch) read it without the project; torch 2.13 deprecates
    TorchScript, so it stays only while torch ships it.
``pt2``
    A ``torch.export`` program (``torch.export.load(path).module()``), TorchScript's successor.
``onnx``
    For runtimes without torch (onnxruntime, ONNX.js, TensorRT, ...).

Every format holds the whole model, the observation normalisation (or an EEG decoder's input
scaling) included, and the same description as JSON (:data:`META_KEY`): TorchScript and
``.pt2`` as an extra file, ONNX as a metadata property.
"""

from __future__ import annotations

from typing import Literal

ModelFormat = Literal["torchscript", "pt2", "onnx"]
MODEL_FORMATS: tuple[ModelFormat, ...] = ("torchscript", "pt2", "onnx")
SUFFIXES: dict[ModelFormat, str] = {"torchscript": ".pt", "pt2": ".pt2", "onnx": ".onnx"}
"""File name ending of each format."""
META_KEY = "bgrl_meta.json"
"""Name of the JSON description inside every model file."""
