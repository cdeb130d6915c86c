"""A calibration's files: the kept classifier, ``history.json``, the report, ``metrics.json``.

They are written to a temporary sibling folder and moved into the output folder at the
end, ``metrics.json`` last (it marks a finished classifier); on any failure that folder is
removed and the output folder is left as it was.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from services.core.files import write_results_json
from services.eeg.decoding.classifier import (
    CONFIG_FILE,
    ONNX_FILE,
    PT2_FILE,
    STATE_FILE,
    TORCHSCRIPT_FILE,
)
from services.eeg.decoding.report import write_report
from services.eeg.decoding.result import CalibrationResult

METRICS_FILE = "metrics.json"
HISTORY_FILE = "history.json"
ARTEFACTS = frozenset(
    {
        CONFIG_FILE,
        STATE_FILE,
        TORCHSCRIPT_FILE,
        PT2_FILE,
        ONNX_FILE,
        HISTORY_FILE,
        "report.png",
        "report.html",
    }
)
"""Files a calibration writes besides ``metrics.json`` (report names:
services.eeg.decoding.report)."""


def write_outputs(result: CalibrationResult, out: Path, *, report: bool, onnx: bool) -> Path:
    """Write the artefacts to a temporary sibling of ``out`` and move them in.

    The classifier is written as TorchScript and as a ``torch.export`` program (``model.pt2``);
    with ``onnx``, ``model.onnx`` too when the kept decoder has an ONNX form
    (:attr:`~services.eeg.decoding.classifier.ErrPClassifier.exports_onnx`).
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    try:
        result.classifier.save(staging)
        result.classifier.export_pt2(staging)
        if onnx and result.classifier.exports_onnx:
            result.classifier.export_onnx(staging)
        write_results_json(staging / HISTORY_FILE, result.history, indent=None)
        if report:
            write_report(result, staging)
        write_results_json(staging / METRICS_FILE, result.metrics)
        out.mkdir(exist_ok=True)
        names = sorted(p.name for p in staging.iterdir() if p.name != METRICS_FILE)
        # metrics.json marks a finished classifier: the old one goes first, and artefacts
        # of an earlier run that this run did not make (model.onnx, report) go too.
        (out / METRICS_FILE).unlink(missing_ok=True)
        for name in ARTEFACTS - set(names):
            (out / name).unlink(missing_ok=True)
        for name in [*names, METRICS_FILE]:
            os.replace(staging / name, out / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return out
