"""xDAWN + Riemannian geometry: a second classical ErrP decoder beside EEGNet and the sLDA.

The standard ERP pipeline of pyriemann (Barachant & Congedo; xDAWN: Rivet et al., IEEE
TBME 2009; ERP covariances and tangent space: Barachant et al., "Classification of
covariance matrices using a Riemannian-based kernel for BCI applications", Neurocomputing
2013; Congedo et al., "Riemannian geometry for EEG-based brain-computer interfaces",
Brain-Computer Interfaces 2017):

1. xDAWN spatial filters, ``N_FILTERS`` per class, fitted on the training epochs
   (``pyriemann.estimation.XdawnCovariances``), project the 64 channels to 4 virtual ones;
2. each epoch's filtered signals are stacked under the two class prototypes (the filtered
   class means of the training epochs) and their covariance is estimated with the oracle
   approximating shrinkage (OAS, Chen et al. 2010): an 8 x 8 SPD matrix per epoch whose
   cross-terms carry the epoch's similarity to each prototype;
3. the matrices are mapped to the tangent space at their Riemannian (affine-invariant)
   mean over the training epochs: ``upper(logm(Cref^-1/2 C Cref^-1/2))`` (off-diagonal
   terms weighted by sqrt 2), 36 features;
4. a logistic regression (scikit-learn, class-balanced weights like EEGNet's loss and the
   sLDA's equal priors) separates error from correct epochs.

pyriemann and scikit-learn fit it (at calibration only); the fitted decoder is one torch
module, :class:`XdawnRiemann` (filters, prototypes, the reference's inverse square root,
OAS, matrix logarithm by ``torch.linalg.eigh``, the linear model), so it is saved, loaded
and exported as TorchScript inside an :class:`~services.eeg.decoding.classifier.ErrPClassifier`
like EEGNet and the sLDA, bound to its channel list and rate, and decoding needs neither
pyriemann nor scikit-learn. ONNX has no eigendecomposition, so this decoder has no ONNX
export.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from services.eeg.decoding.classical import N_CV_FOLDS

N_FILTERS = 2
"""xDAWN filters per class (pyriemann's ERP examples use 2-4)."""
N_CLASSES = 2


def _zeros(*shape: int) -> nn.Parameter:
    """A float64 parameter of zeros, built without any draw from torch's generator."""
    return nn.Parameter(torch.zeros(*shape, dtype=torch.float64))


class XdawnRiemann(nn.Module):
    """Epochs (n, n_chans, n_times) -> logits (correct, error) = (0, w . t + b).

    ``t`` is the tangent vector of the epoch's xDAWN ERP covariance at the training mean.
    Computed in float64 (the matrices are 8 x 8; the cost is the filtering), logits
    returned in the input's dtype.

    Parameters
    ----------
    n_chans, n_times : int
        Shape of one epoch (all channels of the classifier, in its order).
    n_filters : int
        xDAWN filters per class (``n_components = 2 * n_filters`` filtered signals).
    """

    def __init__(self, n_chans: int, n_times: int, n_filters: int = N_FILTERS) -> None:
        super().__init__()
        if n_chans < 1 or n_times < 2 or not 1 <= n_filters <= n_chans:
            raise ValueError(
                f"need n_chans >= 1, n_times >= 2, 1 <= n_filters <= n_chans; got "
                f"{n_chans}, {n_times}, {n_filters}"
            )
        self.n_chans, self.n_times, self.n_filters = int(n_chans), int(n_times), int(n_filters)
        n_components = N_CLASSES * self.n_filters
        size = 2 * n_components  # prototypes stacked over the filtered epoch
        self.filters = _zeros(n_components, self.n_chans)
        self.prototypes = _zeros(n_components, self.n_times)
        self.reference_isqrt = _zeros(size, size)
        rows, cols = torch.triu_indices(size, size)
        weights = torch.where(rows == cols, 1.0, float(np.sqrt(2.0))).to(torch.float64)
        self.register_buffer("triu_rows", rows)
        self.register_buffer("triu_cols", cols)
        self.register_buffer("triu_weights", weights)
        self.linear = nn.Linear(rows.numel(), 1, dtype=torch.float64, device="meta").to_empty(
            device="cpu"
        )
        with torch.no_grad():
            self.linear.weight.zero_()
            self.linear.bias.zero_()

    @property
    def hparams(self) -> dict[str, Any]:
        """Constructor arguments (saved with the classifier)."""
        return {"n_chans": self.n_chans, "n_times": self.n_times, "n_filters": self.n_filters}

    def covariances(self, x: torch.Tensor) -> torch.Tensor:
        """OAS covariance of [prototypes; xDAWN-filtered epoch], (n, 2k, 2k), float64."""
        filtered = torch.matmul(self.filters, x.to(torch.float64))
        stacked = torch.cat([self.prototypes.expand(x.shape[0], -1, -1), filtered], dim=1)
        centered = stacked - stacked.mean(dim=2, keepdim=True)
        n_times, size = stacked.shape[2], stacked.shape[1]
        emp = torch.matmul(centered, centered.transpose(1, 2)) / n_times
        alpha = (emp * emp).mean(dim=(1, 2))
        mu = torch.diagonal(emp, dim1=1, dim2=2).sum(dim=1) / size
        num = alpha + mu * mu
        den = (n_times + 1) * (alpha - mu * mu / size)
        shrinkage = torch.where(den == 0, torch.ones_like(den), torch.clamp(num / den, max=1.0))
        eye = torch.eye(size, dtype=torch.float64, device=x.device)
        return (1.0 - shrinkage)[:, None, None] * emp + (shrinkage * mu)[:, None, None] * eye

    def tangent_vectors(self, x: torch.Tensor) -> torch.Tensor:
        """``upper(logm(Cref^-1/2 C Cref^-1/2))``, (n, k(k+1)/2) with k = 2 * n_components."""
        whitened = torch.matmul(
            torch.matmul(self.reference_isqrt, self.covariances(x)), self.reference_isqrt
        )
        eigenvalues, eigenvectors = torch.linalg.eigh(whitened)
        log = torch.matmul(
            eigenvectors * torch.log(eigenvalues).unsqueeze(1), eigenvectors.transpose(1, 2)
        )
        return log[:, self.triu_rows, self.triu_cols] * self.triu_weights

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        decision = self.linear(self.tangent_vectors(x)).to(x.dtype)
        return torch.cat([torch.zeros_like(decision), decision], dim=1)


@dataclass
class XdawnRiemannFit:
    """A fitted :class:`XdawnRiemann` and its cross-validation on the training epochs."""

    model: XdawnRiemann
    cv_accuracy: list[float]
    """Accuracy of each of the 5 folds (stratified, seeded) on the training epochs."""


def xdawn_riemann_pipeline(n_filters: int = N_FILTERS):
    """The scikit-learn pipeline :class:`XdawnRiemann` reproduces (pyriemann, sklearn)."""
    from pyriemann.estimation import XdawnCovariances
    from pyriemann.tangentspace import TangentSpace
    from sklearn.linear_model import LogisticRegression
    from sklearn.pipeline import make_pipeline

    return make_pipeline(
        XdawnCovariances(nfilter=n_filters, estimator="oas", xdawn_estimator="lwf"),
        TangentSpace(metric="riemann"),
        LogisticRegression(class_weight="balanced", max_iter=1000),
    )


def _inverse_sqrt(matrix: np.ndarray) -> np.ndarray:
    """``matrix^-1/2`` of an SPD matrix (eigendecomposition, as pyriemann's invsqrtm)."""
    eigenvalues, eigenvectors = np.linalg.eigh(matrix)
    return (eigenvectors * eigenvalues**-0.5) @ eigenvectors.T


def fit_xdawn_riemann(
    X: np.ndarray, y: np.ndarray, *, seed: int = 0, n_filters: int = N_FILTERS
) -> XdawnRiemannFit:
    """Fit xDAWN + ERP covariances + tangent space + logistic regression on ``X``.

    Parameters
    ----------
    X : ndarray, shape (n_epochs, n_channels, n_times)
        Training epochs (any fixed scale: the decoder applies to epochs of that scale).
    y : ndarray, shape (n_epochs,)
        1 = error, 0 = correct.
    seed : int
        Seeds the 5-fold cross-validation split.
    n_filters : int
        xDAWN filters per class.
    """
    from sklearn.model_selection import StratifiedKFold

    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y).astype(np.int64)
    if set(np.unique(y)) != {0, 1}:
        raise ValueError("xDAWN needs both correct (0) and error (1) epochs")
    folds = StratifiedKFold(n_splits=N_CV_FOLDS, shuffle=True, random_state=seed)
    cv_accuracy = [
        float(xdawn_riemann_pipeline(n_filters).fit(X[tr], y[tr]).score(X[te], y[te]))
        for tr, te in folds.split(X, y)
    ]
    pipeline = xdawn_riemann_pipeline(n_filters).fit(X, y)
    covariances, tangent, logistic = (step for _, step in pipeline.steps)
    model = XdawnRiemann(X.shape[1], X.shape[2], n_filters)
    with torch.no_grad():
        model.filters.copy_(torch.from_numpy(covariances.Xd_.filters_))
        model.prototypes.copy_(torch.from_numpy(covariances.P_))
        model.reference_isqrt.copy_(torch.from_numpy(_inverse_sqrt(tangent.reference_)))
        model.linear.weight.copy_(torch.from_numpy(logistic.coef_))
        model.linear.bias.copy_(torch.from_numpy(logistic.intercept_))
    return XdawnRiemannFit(model=model.eval(), cv_accuracy=cv_accuracy)
