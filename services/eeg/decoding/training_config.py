"""What a calibration trains (decoders, EEGNet's hyperparameters) and how it is stopped."""

from __future__ import annotations

from dataclasses import dataclass

DECODERS = ("eegnet", "lda", "xdawn_rg")
"""Decoders calibration can train: EEGNet, the window-mean shrinkage LDA
(:mod:`services.eeg.decoding.classical`) and xDAWN + Riemannian geometry
(:mod:`services.eeg.decoding.riemannian`). The order breaks validation ties (earlier wins)."""


class CalibrationCancelled(Exception):  # noqa: N818 (the name callers catch)
    """``should_stop()`` returned True: calibration stopped between two training steps."""


@dataclass(frozen=True)
class TrainingConfig:
    """Hyperparameters of calibration training."""

    lr: float = 1e-3
    """Adam learning rate."""
    weight_decay: float = 0.0
    """Adam L2 penalty."""
    batch_size: int = 32
    """Minibatch size."""
    max_passes: int = 300
    """Upper bound on training passes over the training split."""
    patience: int = 40
    """Stop after this many passes without a lower validation loss."""
    drop_prob: float = 0.25
    """EEGNet dropout probability."""
    kernel_length: int = 32
    """EEGNet temporal kernel length (samples at the feature rate)."""
    decoders: tuple[str, ...] = DECODERS
    """Decoders trained on the same split; the best on validation is kept."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "decoders", tuple(self.decoders))
        unknown = [d for d in self.decoders if d not in DECODERS]
        if not self.decoders or unknown or len(set(self.decoders)) < len(self.decoders):
            raise ValueError(
                f"decoders must be distinct names from {DECODERS}, got {self.decoders}"
            )
