"""A classical ErrP decoder beside EEGNet: window means on fronto-central channels + sLDA.

The standard single-trial ERP pipeline (Blankertz et al., "Single-trial analysis and
classification of ERP components - a tutorial", NeuroImage 2011): the epoch's samples on
nine fronto-central channels are averaged in consecutive 50 ms windows (16 windows over
the paper's [0, 0.8] s epoch, so 144 features with all nine), and a linear discriminant
with Ledoit-Wolf shrinkage of the covariance (scikit-learn's
``LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto")``, equal class priors, as
EEGNet's class-weighted loss) separates error from correct epochs. It uses the epochs
EEGNet uses (the platform's causal preprocessing, identical online), on the same split.

Window means and the discriminant are both linear, so the trained decoder is one small
torch module, :class:`WindowMeanLDA` (channel selection, window-mean matrix, a linear
layer): it is saved, exported (TorchScript, ONNX) and loaded exactly like EEGNet inside an
:class:`~services.eeg.decoding.classifier.ErrPClassifier`, which keeps it bound to its channel list
and sampling rate. No pickled scikit-learn object is ever written or read, so loading a
classifier never unpickles a file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

ERRP_CHANNELS = ("F1", "Fz", "F2", "FC1", "FCz", "FC2", "C1", "Cz", "C2")
"""The nine fronto-central sites around the ErrP's maximum (FCz / Cz); a cap's subset of
them is used when it lacks some (every accepted cap has Fz and Cz)."""
WINDOW_S = 0.05
"""Length of the averaging windows in seconds."""
N_CV_FOLDS = 5


def window_index(n_times: int, sfreq: float, window_s: float = WINDOW_S) -> list[int]:
    """The window of each sample of an epoch: ``floor(k / (sfreq * window_s))``."""
    if n_times < 1 or sfreq <= 0 or window_s <= 0:
        raise ValueError("n_times, sfreq and window_s must be positive")
    return [int(k // (sfreq * window_s + 1e-9)) for k in range(n_times)]


class WindowMeanLDA(nn.Module):
    """Epochs (n, n_chans, n_times) -> logits (correct, error) = (0, w . features + b).

    Parameters
    ----------
    n_chans, n_times : int
        Shape of one epoch (all channels of the classifier, in its order).
    channel_index : sequence of int
        Channels (indices into the epoch) the features are taken from.
    window_index : sequence of int
        Window (0, 1, ...) of every sample; each feature is one channel's mean over one
        window.
    """

    def __init__(
        self,
        n_chans: int,
        n_times: int,
        channel_index: Sequence[int],
        window_index: Sequence[int],
    ) -> None:
        super().__init__()
        channels = [int(c) for c in channel_index]
        windows = [int(w) for w in window_index]
        if not channels or not all(0 <= c < n_chans for c in channels):
            raise ValueError(f"channel_index must be in [0, {n_chans}), got {channels}")
        if len(windows) != n_times or sorted(set(windows)) != list(range(max(windows) + 1)):
            raise ValueError("window_index needs one window per sample, numbered 0, 1, ...")
        self.n_chans, self.n_times = int(n_chans), int(n_times)
        self._channels, self._windows = channels, windows
        n_windows = max(windows) + 1
        means = torch.zeros(n_times, n_windows)
        means[torch.arange(n_times), torch.tensor(windows)] = 1.0
        self.register_buffer("channel_index", torch.tensor(channels, dtype=torch.long))
        self.register_buffer("window_means", means / means.sum(0, keepdim=True))
        # Built on the meta device and zeroed: no draw from torch's global generator (the
        # weights are the LDA's, set by fit_window_lda or load_state_dict).
        linear = nn.Linear(len(channels) * n_windows, 1, device="meta").to_empty(device="cpu")
        with torch.no_grad():
            linear.weight.zero_()
            linear.bias.zero_()
        self.linear = linear

    @property
    def hparams(self) -> dict[str, Any]:
        """Constructor arguments (saved with the classifier)."""
        return {
            "n_chans": self.n_chans,
            "n_times": self.n_times,
            "channel_index": list(self._channels),
            "window_index": list(self._windows),
        }

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """Window means, (n, n_selected * n_windows), channel-major."""
        return torch.matmul(x.index_select(1, self.channel_index), self.window_means).flatten(1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        decision = self.linear(self.features(x))
        return torch.cat([torch.zeros_like(decision), decision], dim=1)


@dataclass
class LDAFit:
    """A fitted :class:`WindowMeanLDA` and its cross-validation on the training epochs."""

    model: WindowMeanLDA
    channels: list[str]
    """Channels the features come from."""
    cv_accuracy: list[float]
    """Accuracy of each of the 5 folds (stratified, seeded) on the training epochs."""


def fit_window_lda(
    X: np.ndarray,
    y: np.ndarray,
    ch_names: Sequence[str],
    sfreq: float,
    *,
    seed: int = 0,
) -> LDAFit:
    """Fit shrinkage LDA on window means of ``X`` (the training epochs, already scaled).

    Parameters
    ----------
    X : ndarray, shape (n_epochs, n_channels, n_times)
        Training epochs (any fixed scale: the decoder applies to epochs of that scale).
    y : ndarray, shape (n_epochs,)
        1 = error, 0 = correct.
    ch_names : sequence of str
        Channel order of ``X``.
    sfreq : float
        Sampling rate of the epochs (Hz).
    seed : int
        Seeds the 5-fold cross-validation split.
    """
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
    from sklearn.model_selection import StratifiedKFold

    names = list(ch_names)
    channels = [c for c in ERRP_CHANNELS if c in names]
    if not channels:
        raise ValueError(f"none of the ErrP channels {ERRP_CHANNELS} is in the recording")
    n_times = X.shape[2]
    model = WindowMeanLDA(
        len(names), n_times, [names.index(c) for c in channels], window_index(n_times, sfreq)
    )
    with torch.no_grad():
        features = model.features(torch.from_numpy(np.ascontiguousarray(X, np.float32)))
    F = features.double().numpy()
    y = np.asarray(y).astype(np.int64)

    def lda() -> LinearDiscriminantAnalysis:
        return LinearDiscriminantAnalysis(solver="lsqr", shrinkage="auto", priors=[0.5, 0.5])

    folds = StratifiedKFold(n_splits=N_CV_FOLDS, shuffle=True, random_state=seed)
    cv_accuracy = [
        float(lda().fit(F[train], y[train]).score(F[test], y[test]))
        for train, test in folds.split(F, y)
    ]
    fitted = lda().fit(F, y)
    with torch.no_grad():
        model.linear.weight.copy_(torch.as_tensor(fitted.coef_, dtype=torch.float32))
        model.linear.bias.copy_(torch.as_tensor(fitted.intercept_, dtype=torch.float32))
    return LDAFit(model=model.eval(), channels=channels, cv_accuracy=cv_accuracy)
