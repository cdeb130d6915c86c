"""A trained ErrP classifier: a decoder + the preprocessing and channels it was trained on.

The decoder is EEGNet, the classical window-mean shrinkage LDA
(:class:`~services.eeg.decoding.classical.WindowMeanLDA`) or xDAWN + Riemannian geometry
(:class:`~services.eeg.decoding.riemannian.XdawnRiemann`); calibration keeps the best of them on
validation. All are torch modules mapping scaled epochs to two logits, so all are saved,
exported as TorchScript and loaded the same way (no pickled objects). ONNX has no
eigendecomposition, so an xDAWN + RG classifier has no ONNX form.

A classifier is only applied to data preprocessed the same way from the same channels at
the same sampling rate; :meth:`ErrPClassifier.check_compatible` enforces it.

On disk (``save(dir)``)::

    dir/classifier.json    architecture, preprocessing params, channels, rate, metrics and
                           the posterior calibration (``calibration``; absent in classifiers
                           calibrated before it existed)
    dir/model.pt           the decoder's state dict
    dir/model.torchscript.pt  TorchScript: epochs in volts (n, n_chans, n_times) -> P(error)
    dir/model.pt2          the same as a torch.export program (``export_pt2``;
                           ``torch.export.load(path).module()``; float32 epochs, any batch)
    dir/model.onnx         the same graph as ONNX (``export_onnx``; input "epochs", output
                           "p_error", dynamic batch), for runtimes without torch (EEGNet
                           and WindowMeanLDA)

Each file holds the decoder with its input scaling (epochs in volts go in) and the
classifier's description (``classifier.json``'s content) as ``bgrl_meta.json``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from services.core.files import write_bytes_atomic
from services.core.model_formats import SUFFIXES
from services.eeg.decoding.classical import WindowMeanLDA
from services.eeg.decoding.eegnet import EEGNet, count_parameters
from services.eeg.decoding.posterior import PosteriorCalibration
from services.eeg.decoding.riemannian import XdawnRiemann
from services.eeg.signal.preprocessing import PreprocessingParams
from services.model_export import export_program, save_onnx, save_pt2

CONFIG_FILE = "classifier.json"
STATE_FILE = "model.pt"
TORCHSCRIPT_FILE = "model.torchscript.pt"
PT2_FILE = "model" + SUFFIXES["pt2"]
ONNX_FILE = "model" + SUFFIXES["onnx"]
FORMAT_VERSION = 1
ARCHITECTURES: dict[str, type[EEGNet] | type[WindowMeanLDA] | type[XdawnRiemann]] = {
    "EEGNet": EEGNet,
    "WindowMeanLDA": WindowMeanLDA,
    "XdawnRiemann": XdawnRiemann,
}
"""Decoders a classifier can hold, by the ``architecture`` name in ``classifier.json``."""
ONNX_ARCHITECTURES = frozenset({"EEGNet", "WindowMeanLDA"})
"""Architectures with an ONNX form (XdawnRiemann's matrix logarithm needs an
eigendecomposition, which ONNX lacks)."""
Decoder = EEGNet | WindowMeanLDA | XdawnRiemann


class ErrorProbability(nn.Module):
    """The decoder wrapped to map epochs in volts to P(error); the exported TorchScript graph."""

    def __init__(self, model: Decoder, input_scale: float) -> None:
        super().__init__()
        self.model = model
        self.input_scale = input_scale

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits = self.model(x * self.input_scale)
        return torch.softmax(logits, dim=1)[:, 1]


class ErrPClassifier:
    """ErrP decoder bound to its preprocessing and channel list.

    Parameters
    ----------
    model : EEGNet, WindowMeanLDA or XdawnRiemann
        Trained decoder with 2 outputs (index 1 = error).
    params : PreprocessingParams
        Preprocessing the training epochs went through.
    ch_names : sequence of str
        Channel order of the epochs.
    sfreq_in : float
        Sampling rate (Hz) of the raw recording before preprocessing.
    input_scale : float
        Factor applied to epochs in volts before the network (1 / training std).
    metrics : dict
        Calibration metrics (``test_accuracy``, ``balanced_accuracy``, ``roc_auc``, ...).
    synthetic : bool
        True when trained on virtual-subject data.
    calibration : PosteriorCalibration | None
        Platt scaling of P(error) fitted on the calibration's validation epochs
        (:mod:`services.eeg.decoding.posterior`); :meth:`posterior` and :meth:`log_likelihood_ratio`
        need it.
    """

    def __init__(
        self,
        model: Decoder,
        params: PreprocessingParams,
        ch_names: Sequence[str],
        sfreq_in: float,
        input_scale: float,
        metrics: dict[str, Any] | None = None,
        *,
        synthetic: bool = False,
        calibration: PosteriorCalibration | None = None,
    ) -> None:
        if model.n_chans != len(ch_names) or model.n_times != params.n_times_epoch:
            raise ValueError(
                f"model expects ({model.n_chans}, {model.n_times}) epochs, preprocessing "
                f"gives ({len(ch_names)}, {params.n_times_epoch})"
            )
        self.model = model.eval()
        self.params = params
        self.ch_names = list(ch_names)
        self.sfreq_in = float(sfreq_in)
        self.input_scale = float(input_scale)
        self.metrics: dict[str, Any] = dict(metrics or {})
        self.synthetic = synthetic
        self.calibration = calibration
        self._proba = ErrorProbability(self.model, self.input_scale).eval()

    @property
    def n_params(self) -> int:
        return count_parameters(self.model)

    @property
    def architecture(self) -> str:
        """``EEGNet``, ``WindowMeanLDA`` or ``XdawnRiemann``."""
        return type(self.model).__name__

    @property
    def exports_onnx(self) -> bool:
        """Whether :meth:`export_onnx` can write this decoder (not XdawnRiemann)."""
        return self.architecture in ONNX_ARCHITECTURES

    @property
    def epoch_shape(self) -> tuple[int, int]:
        """(n_channels, n_times) of one epoch."""
        return len(self.ch_names), self.params.n_times_epoch

    def check_compatible(self, ch_names: Sequence[str], sfreq: float) -> None:
        """Raise ``ValueError`` unless data with these channels and rate can be classified.

        Parameters
        ----------
        ch_names : sequence of str
            Channels of the incoming data, in order.
        sfreq : float
            Sampling rate (Hz) of the incoming raw data.
        """
        if not np.isclose(float(sfreq), self.sfreq_in):
            raise ValueError(
                f"sampling rate {sfreq} Hz does not match the classifier's {self.sfreq_in} Hz"
            )
        names = list(ch_names)
        if names != self.ch_names:
            missing = [c for c in self.ch_names if c not in names]
            extra = [c for c in names if c not in self.ch_names]
            if missing or extra:
                raise ValueError(
                    f"channels do not match the classifier's: missing {missing[:8]}, "
                    f"unexpected {extra[:8]} ({len(names)} given, {len(self.ch_names)} expected)"
                )
            raise ValueError("channels are the classifier's but in a different order")

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        """P(error) per epoch.

        Parameters
        ----------
        X : ndarray, shape (n_epochs, n_channels, n_times) or (n_channels, n_times)
            Preprocessed epochs in volts, channels in ``ch_names`` order.

        Returns
        -------
        ndarray, shape (n_epochs,), float64
        """
        X = np.asarray(X, dtype=np.float32)
        if X.ndim == 2:
            X = X[None]
        if X.ndim != 3 or X.shape[1:] != self.epoch_shape:
            raise ValueError(f"expected epochs of shape (n, {self.epoch_shape}), got {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ValueError("epochs contain NaN or infinite values")
        with torch.inference_mode():
            return self._proba(torch.from_numpy(X)).double().numpy()

    def _posterior_calibration(self) -> PosteriorCalibration:
        if self.calibration is None:
            raise ValueError(
                "this classifier has no posterior calibration (it was calibrated before "
                "calibrated outputs existed): calibrate it again"
            )
        return self.calibration

    def posterior(self, X: np.ndarray) -> np.ndarray:
        """Calibrated P(error | epoch) per epoch, at the calibration session's error rate."""
        return self._posterior_calibration().posterior(self.predict_proba(X))

    def log_likelihood_ratio(self, X: np.ndarray) -> np.ndarray:
        """``log P(epoch | error) / P(epoch | correct)`` per epoch: the soft label stage 2
        takes (:meth:`PosteriorCalibration.log_likelihood_ratio
        <services.eeg.decoding.posterior.PosteriorCalibration.log_likelihood_ratio>`)."""
        return self._posterior_calibration().log_likelihood_ratio(self.predict_proba(X))

    def decode_epoch(self, epoch: np.ndarray) -> tuple[float, float | None]:
        """One epoch's raw P(error) (whose threshold gives the hard label) and its
        log-likelihood ratio (None without a posterior calibration)."""
        p_error = self.predict_proba(epoch)[:1]
        if self.calibration is None:
            return float(p_error[0]), None
        return float(p_error[0]), float(self.calibration.log_likelihood_ratio(p_error)[0])

    def predict(self, X: np.ndarray, threshold: float = 0.5) -> np.ndarray:
        """1 (error) where P(error) >= ``threshold``, else 0 (correct)."""
        return (self.predict_proba(X) >= threshold).astype(np.int64)

    def to_config(self) -> dict[str, Any]:
        """JSON-serialisable description (everything but the weights)."""
        m = self.model
        return {
            "format_version": FORMAT_VERSION,
            "architecture": self.architecture,
            "model_kwargs": m.hparams,
            "preprocessing": self.params.model_dump(),
            "ch_names": self.ch_names,
            "sfreq_in": self.sfreq_in,
            "input_scale": self.input_scale,
            "synthetic": self.synthetic,
            "metrics": self.metrics,
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
        }

    def save(self, directory: str | Path) -> Path:
        """Write the classifier (config, weights, TorchScript) to ``directory``."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        torch.save(self.model.state_dict(), directory / STATE_FILE)
        torch.jit.script(self._proba).save(str(directory / TORCHSCRIPT_FILE))
        write_bytes_atomic(directory / CONFIG_FILE, json.dumps(self.to_config(), indent=2).encode())
        return directory

    def _program(self) -> torch.export.ExportedProgram:
        """The P(error) module traced by ``torch.export`` for any batch size."""
        example = torch.zeros((2, *self.epoch_shape), dtype=torch.float32)
        return export_program(self._proba, example)

    def export_pt2(self, directory: str | Path) -> Path:
        """Write ``model.pt2``, a ``torch.export`` program (float32 epochs in volts ->
        P(error), any batch size), to ``directory``; every decoder has this form."""
        return save_pt2(self._program(), Path(directory) / PT2_FILE, self.to_config())

    def export_onnx(self, directory: str | Path) -> Path:
        """Write ``model.onnx`` (epochs in volts -> P(error), any batch size) to ``directory``.

        Uses torch's dynamo exporter (needs ``onnx`` and ``onnxscript``; runs offline) and
        takes a few seconds, so it is separate from :meth:`save`. ``ValueError`` for a
        decoder without an ONNX form (:attr:`exports_onnx`).
        """
        if not self.exports_onnx:
            raise ValueError(
                f"a {self.architecture} classifier has no ONNX form (its matrix logarithm "
                "needs an eigendecomposition, which ONNX lacks); use its TorchScript file"
            )
        return save_onnx(
            self._program(),
            Path(directory) / ONNX_FILE,
            self.to_config(),
            input_name="epochs",
            output_name="p_error",
        )

    @classmethod
    def load(cls, directory: str | Path) -> ErrPClassifier:
        """Load a classifier written by :meth:`save`; ``ValueError`` if it is unusable."""
        directory = Path(directory)
        config_path = directory / CONFIG_FILE
        if not config_path.is_file():
            raise ValueError(f"no classifier in {directory} ({CONFIG_FILE} missing)")
        config = json.loads(config_path.read_text())
        if config.get("format_version") != FORMAT_VERSION:
            raise ValueError(f"unsupported classifier format {config.get('format_version')}")
        architecture = ARCHITECTURES.get(config.get("architecture", ""))
        if architecture is None:
            raise ValueError(
                f"unknown classifier architecture {config.get('architecture')!r}; "
                f"expected one of {sorted(ARCHITECTURES)}"
            )
        model = architecture(**config["model_kwargs"])
        state = torch.load(directory / STATE_FILE, map_location="cpu", weights_only=True)
        model.load_state_dict(state)
        return cls(
            model,
            PreprocessingParams(**config["preprocessing"]),
            config["ch_names"],
            config["sfreq_in"],
            config["input_scale"],
            config["metrics"],
            synthetic=config["synthetic"],
            calibration=(
                None
                if config.get("calibration") is None
                else PosteriorCalibration.from_dict(config["calibration"])
            ),
        )
