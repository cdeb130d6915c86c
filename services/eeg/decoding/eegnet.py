"""EEGNet with valid padding, the ErrP classifier of the paper (slimmed: F1=4, D=2, F2=4)."""

from __future__ import annotations

import math

import torch
from torch import nn

SPATIAL_MAX_NORM = 1.0
"""Max L2 norm of each depthwise spatial kernel (Lawhern et al.)."""
DENSE_MAX_NORM = 0.25
"""Max L2 norm of each row of the dense classifier (Lawhern et al.)."""


class GeneratorDropout(nn.Dropout):
    """``nn.Dropout`` that draws its masks from :attr:`generator` (a local ``torch.Generator``).

    With ``generator`` None it is ``nn.Dropout``, drawing from torch's global generator. The
    mask is computed as torch's CPU dropout computes it (``bernoulli_(1 - p)``, divided by
    ``1 - p``), so a generator seeded like the global one gives the same masks.
    """

    def __init__(self, p: float = 0.5) -> None:
        super().__init__(p)
        self.generator: torch.Generator | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        if torch.jit.is_scripting():  # TorchScript has no generator: global draws
            return nn.functional.dropout(x, self.p, True)
        if self.p >= 1.0:
            return x * 0.0
        noise = torch.empty_like(x).bernoulli_(1.0 - self.p, generator=self.generator)
        noise.div_(1.0 - self.p)
        return x * noise


class EEGNet(nn.Module):
    """EEGNet (Lawhern et al., 2018) with *valid* padding, as modified by Akinola et al.

    Block 1: temporal convolution (``F1`` kernels of ``kernel_length`` samples), batch
    norm, depthwise spatial convolution over all channels (``D`` per temporal filter),
    batch norm, ELU, average pooling by ``pool1``, dropout. Block 2: separable convolution
    (depthwise ``separable_kernel_length`` then pointwise to ``F2``), batch norm, ELU,
    average pooling by ``pool2``, dropout. Classifier: flatten, dense layer. All
    convolutions use valid padding (paper footnote). The max-norm constraints of Lawhern
    et al. (1 on spatial kernels, 0.25 on the dense layer) are applied by
    :meth:`apply_max_norm` after each optimiser step, so the forward pass stays scriptable.

    With the defaults and 103 samples (0.8 s at 128 Hz) the time axis shrinks exactly:
    103 -> 72 (temporal conv, 32) -> 18 (pool 4) -> 12 (separable, 7) -> 3 (pool 4), so
    the classifier sees ``F2 * 3 = 12`` features. For 64 channels and 2 outputs the network
    has 786 trainable parameters.

    Parameters
    ----------
    n_chans : int
        Number of EEG channels.
    n_outputs : int
        Number of classes (logits returned).
    n_times : int
        Samples per epoch.
    F1 : int
        Number of temporal filters.
    D : int
        Spatial filters per temporal filter (depth multiplier).
    F2 : int
        Number of pointwise filters in the separable convolution.
    kernel_length : int
        Temporal kernel length in samples (32 = 250 ms at 128 Hz).
    drop_prob : float
        Dropout probability after each block.
    separable_kernel_length : int
        Temporal length of the separable convolution's depthwise kernel.
    pool1, pool2 : int
        Average pooling factors along time after block 1 and block 2.

    References
    ----------
    .. [1] Lawhern, V. J. et al. (2018). EEGNet: a compact convolutional neural network
       for EEG-based brain-computer interfaces. J. Neural Eng. 15, 056013.
    .. [2] Akinola, I. et al. (2020). Accelerated Robot Learning via Human Brain Signals.
       ICRA 2020.
    """

    def __init__(
        self,
        n_chans: int,
        n_outputs: int,
        n_times: int,
        F1: int = 4,
        D: int = 2,
        F2: int = 4,
        kernel_length: int = 32,
        *,
        drop_prob: float = 0.25,
        separable_kernel_length: int = 7,
        pool1: int = 4,
        pool2: int = 4,
    ) -> None:
        super().__init__()
        t1 = n_times - kernel_length + 1
        t2 = t1 // pool1 - separable_kernel_length + 1
        t3 = t2 // pool2
        if t1 < 1 or t2 < 1 or t3 < 1:
            raise ValueError(
                f"n_times={n_times} is too short for kernel_length={kernel_length}, "
                f"pool1={pool1}, separable_kernel_length={separable_kernel_length}, "
                f"pool2={pool2} with valid padding"
            )
        self.n_chans, self.n_outputs, self.n_times = n_chans, n_outputs, n_times
        self.hparams = {
            "n_chans": n_chans,
            "n_outputs": n_outputs,
            "n_times": n_times,
            "F1": F1,
            "D": D,
            "F2": F2,
            "kernel_length": kernel_length,
            "drop_prob": drop_prob,
            "separable_kernel_length": separable_kernel_length,
            "pool1": pool1,
            "pool2": pool2,
        }
        """Constructor arguments, enough to rebuild the network (saved with classifiers)."""
        self.n_features = F2 * t3
        self.conv_temporal = nn.Conv2d(1, F1, (1, kernel_length), bias=False)
        self.bnorm_temporal = nn.BatchNorm2d(F1)
        self.conv_spatial = nn.Conv2d(F1, F1 * D, (n_chans, 1), groups=F1, bias=False)
        self.bnorm_1 = nn.BatchNorm2d(F1 * D)
        self.elu_1 = nn.ELU()
        self.pool_1 = nn.AvgPool2d((1, pool1))
        self.drop_1 = GeneratorDropout(drop_prob)
        self.conv_separable_depth = nn.Conv2d(
            F1 * D, F1 * D, (1, separable_kernel_length), groups=F1 * D, bias=False
        )
        self.conv_separable_point = nn.Conv2d(F1 * D, F2, (1, 1), bias=False)
        self.bnorm_2 = nn.BatchNorm2d(F2)
        self.elu_2 = nn.ELU()
        self.pool_2 = nn.AvgPool2d((1, pool2))
        self.drop_2 = GeneratorDropout(drop_prob)
        self.final_layer = nn.Linear(self.n_features, n_outputs)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Logits of shape (batch, n_outputs) for ``x`` of shape (batch, n_chans, n_times)."""
        x = x.unsqueeze(1)
        x = self.bnorm_temporal(self.conv_temporal(x))
        x = self.drop_1(self.pool_1(self.elu_1(self.bnorm_1(self.conv_spatial(x)))))
        x = self.conv_separable_point(self.conv_separable_depth(x))
        x = self.drop_2(self.pool_2(self.elu_2(self.bnorm_2(x))))
        return self.final_layer(torch.flatten(x, 1))

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """(Re)initialise every layer as torch's constructors do, drawing from ``generator``.

        Convolutions and the dense layer get ``kaiming_uniform_(a=sqrt(5))`` weights (and
        the dense bias ``U(+-1/sqrt(fan_in))``) in construction order, batch norms ones and
        zeros; so a generator seeded with ``s`` gives the weights that ``torch.manual_seed(s)``
        followed by the constructor gives, without touching the global generator.
        """
        for module in self.modules():
            if isinstance(module, nn.Conv2d | nn.Linear):
                nn.init.kaiming_uniform_(module.weight, a=math.sqrt(5), generator=generator)
                if module.bias is not None:
                    fan_in, _ = nn.init._calculate_fan_in_and_fan_out(module.weight)
                    bound = 1.0 / math.sqrt(fan_in) if fan_in > 0 else 0.0
                    nn.init.uniform_(module.bias, -bound, bound, generator=generator)
            elif isinstance(module, nn.BatchNorm2d):
                module.reset_parameters()

    def set_dropout_generator(self, generator: torch.Generator | None) -> None:
        """Draw dropout masks from ``generator`` (None: torch's global generator)."""
        for module in self.modules():
            if isinstance(module, GeneratorDropout):
                module.generator = generator

    @torch.no_grad()
    def apply_max_norm(self) -> None:
        """Renormalise the spatial and dense weights; call after every optimiser step."""
        w = self.conv_spatial.weight
        w.copy_(torch.renorm(w, p=2, dim=0, maxnorm=SPATIAL_MAX_NORM))
        w = self.final_layer.weight
        w.copy_(torch.renorm(w, p=2, dim=0, maxnorm=DENSE_MAX_NORM))


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
